"""The image-health watch's shell in the capture process (the core: trapflow.image_health).

Capture holds every image, so it samples one left image every `image_health.every_s` of
capture time, logs a change of state once (not per pair), and keeps the learnt baseline in
the run directory (image_health.json), so a capture restarted in the same deployment
compares with the first minutes of the deployment, not with a lens already fouled.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from trapflow.config.image_health import ImageHealthConfig
from trapflow.image_health.measure import Sample, measure
from trapflow.image_health.watch import Change, Watch
from trapflow.runtime.files import write_atomically
from trapflow.wire.messages import ImageHealth

log = logging.getLogger(__name__)

BASELINE_FILE = "image_health.json"


def load_baseline(path: Path, width: int, size: tuple[int, int]) -> Sample | None:
    """The baseline a previous capture of this run learnt, if it was learnt alike (same
    reduced width, same image size); None otherwise."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        if data["width"] != width or tuple(data["size"]) != size:
            log.info("image health: %s was learnt at another size; learning again", path.name)
            return None
        return Sample(sharpness=float(data["sharpness"]), contrast=float(data["contrast"]),
                      brightness=float(data["brightness"]))
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("image health: cannot read %s (%s); learning the baseline again", path, exc)
        return None


class ImageWatch:
    """Samples pairs as the watch asks, logs its changes, keeps its baseline."""

    def __init__(self, cfg: ImageHealthConfig, run_dir: Path, size: tuple[int, int]) -> None:
        self.cfg = cfg
        self.path = run_dir / BASELINE_FILE
        self.size = size
        baseline = load_baseline(self.path, cfg.width, size)
        self.watch = Watch(cfg, baseline)
        if baseline is not None:
            log.info("image health: the deployment's baseline from %s", self.path.name)

    def pair(self, left: np.ndarray, t_s: float) -> ImageHealth | None:
        """The watch's view after sampling this left image (captured at t_s, seconds on a
        clock no wall-clock step moves), or None when it is not due."""
        if not self.watch.due(t_s):
            return None
        had_baseline = self.watch.baseline is not None
        change = self.watch.add(t_s, measure(left, self.cfg.width))
        if not had_baseline and self.watch.baseline is not None:
            self._save(self.watch.baseline)
        if change is not None:
            self._log(change)
        return self.watch.view

    def _save(self, b: Sample) -> None:
        data = {"width": self.cfg.width, "size": list(self.size), "sharpness": b.sharpness,
                "contrast": b.contrast, "brightness": b.brightness}
        try:
            write_atomically(self.path, json.dumps(data).encode())
        except OSError as exc:  # a full disk: the watch goes on; a restart learns again
            log.warning("image health: cannot keep the baseline in %s: %s", self.path, exc)

    @staticmethod
    def _log(change: Change) -> None:
        v = change.view
        ratios = (f"sharpness {v.sharpness:.2f}, contrast {v.contrast:.2f}, brightness "
                  f"{v.brightness:.2f} of the baseline")
        if change.old == "learning":
            log.info("image health: baseline learnt from %d samples; %s", v.samples, v.state)
        elif v.state == "ok":
            log.info("image health: ok again (was %s): %s", change.old, ratios)
        else:
            log.warning("image health: %s (was %s): %s", v.state, change.old, ratios)
