"""Benchmark of the stereo VO plugin against an earlier revision of it, in one run: CPU per pair
by stage at 1280x720 on the moving synthetic world, and drift on the independent scene of
tests/conformance/test_vo_scene.py.

The earlier plugin is read from git (`git show REV:workers/stereo_vo.py`) into a temporary
module; each pair goes through both plugins in turn, so load on the machine falls on both
alike. CPU is process time with one OpenCV thread. Stages are timed by wrapping the OpenCV
calls the plugin makes. Writes vo.json and vo.md into --out.

Usage: python -m benchmarks.vo [--quick] [--pairs 120] [--before REV] [--no-drift]
       [--out bench-results]        (--quick: 40 pairs, no drift)
"""

from __future__ import annotations

import hashlib
import importlib.util
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
import numpy as np

from benchmarks import harness as h
from tests.conformance import vo_scene
from tests.conformance.test_vo_scene import _inv, drift
from trapflow.calibration.camera import StereoRig
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.testing.kit import make_context, make_pair

REPO = Path(__file__).resolve().parents[1]
# The plugin before the CPU work of issue 27 (24.8 ms a pair at 1280x720 in the CPU bench).
BEFORE = "8a163db"

# OpenCV call -> stage; an LK call inside a keyframe is stereo matching, else tracking.
STAGES = {
    "goodFeaturesToTrack": "detection",
    "calcOpticalFlowPyrLK": "lk",
    "phaseCorrelate": "stereo matching",
    "solvePnPRansac": "PnP RANSAC",
    "solvePnPRefineLM": "final fit",
    "projectPoints": "final fit",
}
ORDER = ("detection", "KLT tracking", "stereo matching", "PnP RANSAC", "final fit", "other")


class _Timed:
    """Stands in for the cv2 module inside one plugin module: times the calls of STAGES."""

    def __init__(self, acc: dict[str, float], where: list[str]) -> None:
        self._acc, self._where = acc, where

    def __getattr__(self, name: str) -> Any:
        real = getattr(cv2, name)
        stage = STAGES.get(name)
        if stage is None:
            return real

        def timed(*a: Any, **kw: Any) -> Any:
            t = time.process_time()
            out = real(*a, **kw)
            s = stage
            if s == "lk":
                s = "stereo matching" if "keyframe" in self._where else "KLT tracking"
            self._acc[s] += time.process_time() - t
            return out

        return timed


def _previous(rev: str, tmp: Path) -> ModuleType | None:
    """workers/stereo_vo.py at `rev` as a module beside the current plugin; None without git
    or when it no longer imports beside today's workers/."""
    try:
        src = subprocess.run(["git", "show", f"{rev}:workers/stereo_vo.py"], cwd=REPO,
                             check=True, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        print(f"no earlier plugin at {rev}: {exc}", file=sys.stderr)
        return None
    src = src.replace("from .", "from trapflow_workers.")
    path = tmp / "stereo_vo_before.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("stereo_vo_before", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    try:
        spec.loader.exec_module(mod)
    except ImportError as exc:  # it imports what workers/ no longer has: now alone
        print(f"the plugin at {rev} does not import beside today's workers/: {exc}",
              file=sys.stderr)
        del sys.modules[spec.name]
        return None
    return mod


def _instrument(mod: ModuleType) -> tuple[dict[str, float], Callable[[], None]]:
    """Per-stage CPU of one plugin module; returns the accumulator and a reset."""
    acc: dict[str, float] = defaultdict(float)
    where: list[str] = []
    mod.cv2 = _Timed(acc, where)  # type: ignore[attr-defined]
    cls = mod.StereoOdometry
    inner = cls._keyframe

    def keyframe(self: Any, *a: Any, **kw: Any) -> Any:
        where.append("keyframe")
        try:
            return inner(self, *a, **kw)
        finally:
            where.pop()

    cls._keyframe = keyframe
    return acc, acc.clear


def _synthetic(n: int) -> tuple[StereoRig, list[tuple[np.ndarray, np.ndarray]]]:
    rig = StereoRig.from_fov(1280, 720, 70.0, 0.12)
    world = World(rig, seed=1, moving=True, rate_hz=15.0, options=SynthOptions(density=1.5))
    return rig, [world.render(i)[:2] for i in range(n)]


def _cpu(mods: dict[str, ModuleType], rig: StereoRig,
         frames: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    """CPU ms per pair (mean over pairs after the first) and per stage, every pair through
    every plugin in turn."""
    cv2.setNumThreads(1)
    plugins, accs = {}, {}
    for name, mod in mods.items():
        accs[name] = _instrument(mod)[0]
        plugins[name] = mod.StereoOdometry()
        plugins[name].configure({}, make_context(rig, pool="vo"))
    total = {k: 0.0 for k in mods}
    stages: dict[str, dict[str, float]] = {k: defaultdict(float) for k in mods}
    for i, (left, right) in enumerate(frames):
        for name, vo in plugins.items():
            accs[name].clear()
            t = time.process_time()
            vo.process(make_pair(left, right, seq=i))
            dt = time.process_time() - t
            if i == 0:
                continue  # the first pair only initialises
            total[name] += dt
            for s, v in accs[name].items():
                stages[name][s] += v
            stages[name]["other"] += dt - sum(accs[name].values())
    n = len(frames) - 1
    return {name: {"ms_per_pair": 1000 * total[name] / n,
                   "stages_ms": {s: 1000 * stages[name].get(s, 0.0) / n for s in ORDER}}
            for name in mods} | {"pairs": n}


def _scene_cache() -> Path:
    """Where the conformance test keeps the scene's PNG pairs (rendered if missing)."""
    key = hashlib.sha256(Path(vo_scene.__file__).read_bytes()).hexdigest()[:16]
    cache = REPO / ".pytest_cache" / "d" / f"vo_scene_{key}"
    cache.mkdir(parents=True, exist_ok=True)
    return cache


def _drift(mods: dict[str, ModuleType]) -> dict[str, Any]:
    """Drift (%, deg/m) per sequence of the conformance scene, and CPU ms per pair at 752x480."""
    cv2.setNumThreads(1)
    out: dict[str, Any] = {}
    for seq in sorted(vo_scene.SEQUENCES):
        truth, files = vo_scene.sequence(seq, _scene_cache())
        truth = [_inv(truth[0]) @ t for t in truth]
        plugins = {name: mod.StereoOdometry() for name, mod in mods.items()}
        for vo in plugins.values():
            vo.configure({}, make_context(vo_scene.RIG, pool="vo"))
        poses: dict[str, list[np.ndarray]] = {name: [] for name in mods}
        cpu = {name: 0.0 for name in mods}
        for i, f in enumerate(files):
            left, right = vo_scene.load_pair(f)
            for name, vo in plugins.items():
                t = time.process_time()
                res = vo.process(make_pair(left, right, seq=i))
                cpu[name] += time.process_time() - t if i else 0.0
                pose = np.eye(4)
                pose[:3, :4] = np.reshape(res.pose, (3, 4))
                poses[name].append(pose)
        for name in mods:
            pct, deg = drift(truth, poses[name])
            out.setdefault(seq, {})[name] = {"drift_pct": pct, "drift_deg_per_m": deg,
                                             "ms_per_pair": 1000 * cpu[name] / (len(files) - 1)}
    return out


def results(r: dict[str, Any]) -> list[h.Result]:
    """CPU per stage of each plugin, and drift on the conformance scene when it ran."""
    names = list(r["plugins"])
    cpu = r["cpu"]
    t = h.Result("vo", f"Stereo VO CPU per pair, 1280x720 synthetic world ({cpu['pairs']} "
                 "pairs, one OpenCV thread, each pair through both plugins in turn)",
                 key="stage", data=r)
    for s in ORDER:
        t.add(s, **{n: h.Figure(cpu[n]["stages_ms"][s], "ms") for n in names})
    t.add("**total**", **{n: h.Figure(f"**{cpu[n]['ms_per_pair']:.2f}**", "ms") for n in names})
    if "before" in names:
        ratio = cpu["now"]["ms_per_pair"] / cpu["before"]["ms_per_pair"]
        t.notes.append(f"now / before: **{ratio:.2f}x** (before = {r['before_rev']})")
    if not r["drift"]:
        return [t]
    d = h.Result("vo", key="sequence, plugin", notes=[
        "Drift on tests/conformance/test_vo_scene.py (752x480) and CPU ms per pair there "
        "(each pair through both plugins in turn)."])
    for seq, by in r["drift"].items():
        for n in names:
            x = by[n]
            d.add(f"{seq}, {n}", drift=h.Figure(x["drift_pct"], "%", digits=3),
                  **{"drift per metre": h.Figure(x["drift_deg_per_m"], "deg/m", digits=4),
                     "CPU": h.Figure(x["ms_per_pair"], "ms/pair")})
    return [t, d]


def main() -> None:
    ap = h.options(__doc__, repeats=1, quick_help="40 pairs, no drift")
    ap.add_argument("--pairs", type=int, default=120, help="synthetic pairs at 1280x720")
    ap.add_argument("--before", default=BEFORE, help="git revision of the plugin to compare")
    ap.add_argument("--no-drift", action="store_true", help="skip the conformance scene")
    args = ap.parse_args()
    if args.quick:
        args.pairs, args.no_drift = 40, True
    import trapflow_workers.stereo_vo as now

    with tempfile.TemporaryDirectory() as tmp:
        mods: dict[str, ModuleType] = {}
        before = _previous(args.before, Path(tmp))
        if before is not None:
            mods["before"] = before
        mods["now"] = now
        rig, frames = _synthetic(args.pairs)
        report: dict[str, Any] = {"plugins": list(mods), "before_rev": args.before,
                                  "cpu": _cpu(mods, rig, frames)}
        report["drift"] = {} if args.no_drift else _drift(mods)
    tables = results(report)
    h.write(args.out, "vo", tables)
    print(h.markdown(tables))


if __name__ == "__main__":
    main()
