"""Image health (issue 33): the watch's baseline, medians, hold and hysteresis on made-up
samples, and fouling and turbidity told apart on images the synthetic world renders."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from trapflow.calibration.camera import StereoRig
from trapflow.capture.image_watch import BASELINE_FILE, ImageWatch
from trapflow.cli.status_text import image_text
from trapflow.config.image_health import ImageHealthConfig
from trapflow.config.modem import HealthConfig
from trapflow.image_health.measure import Sample, measure
from trapflow.image_health.watch import Watch
from trapflow.modem.codec import LinkCodec
from trapflow.modem.health import HealthMonitor
from trapflow.synth.murk import ramp
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.wire.messages import ImageHealth

RIG = StereoRig.from_fov(320, 240, 70.0, 0.12)
CLEAN = Sample(sharpness=1.2, contrast=0.5, brightness=110.0)
# Short windows for made-up samples one second apart.
SHORT = ImageHealthConfig(every_s=1.0, baseline_s=10.0, window_s=5.0, hold_s=10.0)


def _feed(watch: Watch, samples: list[Sample], t0: float = 0.0) -> list[tuple[float, str]]:
    """Each sample one second after the last; the (time, new state) of every change."""
    out = []
    for i, s in enumerate(samples):
        change = watch.add(t0 + i, s)
        if change is not None:
            out.append((t0 + i, change.view.state))
    return out


def _scaled(s: Sample, sharp: float = 1.0, contrast: float = 1.0, bright: float = 1.0
            ) -> Sample:
    return Sample(sharpness=s.sharpness * sharp, contrast=s.contrast * contrast,
                  brightness=s.brightness * bright)


# --- the watch, on made-up samples ---------------------------------------------------


def test_learning_until_the_baseline_window_has_passed() -> None:
    watch = Watch(SHORT)
    assert _feed(watch, [CLEAN] * 10) == []
    assert watch.view.state == "learning" and watch.view.samples == 10
    assert _feed(watch, [CLEAN], t0=10) == [(10, "ok")]
    assert watch.view.sharpness == watch.view.contrast == watch.view.brightness == 1.0


def test_fouling_is_flagged_after_the_hold_and_cleared_with_hysteresis() -> None:
    watch = Watch(SHORT)
    _feed(watch, [CLEAN] * 11)
    fouled = _scaled(CLEAN, sharp=0.3)
    changes = _feed(watch, [fouled] * 20, t0=11)
    # The window's median turns at its third fouled sample (t 13), then the hold of 10 s.
    assert changes == [(23, "fouled")]
    assert watch.view.sharpness == pytest.approx(0.3) and watch.view.contrast == 1.0
    # Between fouled_below and fouled_clear: still fouled, however long.
    assert _feed(watch, [_scaled(CLEAN, sharp=0.6)] * 30, t0=31) == []
    back = _feed(watch, [CLEAN] * 20, t0=61)
    assert back == [(73, "ok")] and watch.view.changes == 2


def test_turbidity_and_fouling_are_separate_flags() -> None:
    watch = Watch(SHORT)
    _feed(watch, [CLEAN] * 11)
    assert _feed(watch, [_scaled(CLEAN, contrast=0.4)] * 15, t0=11)[-1][1] == "turbid"
    both = _feed(watch, [_scaled(CLEAN, sharp=0.3, contrast=0.4)] * 15, t0=26)
    assert both[-1][1] == "fouled+turbid"


@pytest.mark.parametrize("passing", [
    _scaled(CLEAN, sharp=0.2, contrast=0.3, bright=0.5),  # a crab filling the frame
    _scaled(CLEAN, sharp=3.0, contrast=1.5, bright=0.1),  # the lamp off: dark, noisy
])
def test_what_passes_for_less_than_half_the_window_never_flags(passing: Sample) -> None:
    watch = Watch(SHORT)
    _feed(watch, [CLEAN] * 11)
    # Two odd samples in every five: the medians stay on the clean ones.
    samples = [passing if i % 5 < 2 else CLEAN for i in range(200)]
    assert _feed(watch, samples, t0=11) == [] and watch.view.state == "ok"


def test_a_moment_beyond_the_threshold_shorter_than_the_hold_never_flags() -> None:
    watch = Watch(SHORT)
    _feed(watch, [CLEAN] * 11)
    odd = [_scaled(CLEAN, sharp=0.2)] * 8 + [CLEAN] * 10  # the median low for 8 s of 10
    assert _feed(watch, odd * 3, t0=11) == []


def test_a_given_baseline_is_compared_with_at_once() -> None:
    watch = Watch(SHORT, baseline=CLEAN)
    assert watch.view.state == "ok"
    assert _feed(watch, [_scaled(CLEAN, sharp=0.3)] * 15)[-1] == (10, "fouled")


def test_due_one_sample_every_every_s() -> None:
    watch = Watch(ImageHealthConfig(every_s=10.0))
    assert watch.due(5.0)
    watch.add(5.0, CLEAN)
    assert not watch.due(14.9) and watch.due(15.0)


def test_clear_levels_must_be_above_the_flag_levels() -> None:
    with pytest.raises(ValueError, match="hysteresis"):
        ImageHealthConfig(fouled_below=0.5, fouled_clear=0.5)


# --- the synthetic world: fouling and turbidity, and what must not flag ------------------

ONSET, RAMP = 1200.0, 3600.0  # 20 minutes into the deployment, full an hour later


def _world(**opts: float) -> World:
    return World(RIG, seed=3, moving=False, rate_hz=1.0,
                 options=SynthOptions(density=0, snow=0, **opts))  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def worlds() -> dict[str, World]:
    """The same static floor clean, fouling and turning turbid from ONSET over RAMP."""
    return {"clean": _world(),
            "fouling": _world(fouling_onset_s=ONSET, fouling_ramp_s=RAMP),
            "turbidity": _world(turbidity_onset_s=ONSET, turbidity_ramp_s=RAMP)}


def test_the_world_is_untouched_before_the_onset(worlds: dict[str, World]) -> None:
    clean = worlds["clean"].render(1199)[0]
    for what in ("fouling", "turbidity"):
        assert np.array_equal(worlds[what].render(1199)[0], clean)
        assert not np.array_equal(worlds[what].render(1300)[0], clean)
    assert not worlds["clean"].murk.enabled
    assert ramp(50, None, 10) == 0.0 and ramp(5, 0, 10) == 0.5 and ramp(5, 1, 0) == 1.0


def _ratios(world: World, level: float) -> tuple[float, float]:
    base, now = measure(world.render(0)[0]), measure(world.render(int(ONSET + level * RAMP))[0])
    return now.sharpness / base.sharpness, now.contrast / base.contrast


@pytest.mark.parametrize(("level", "sharp_below"), [(0.5, 0.75), (0.75, 0.4), (1.0, 0.25)])
def test_fouling_takes_sharpness_and_leaves_contrast(worlds: dict[str, World], level: float,
                                                     sharp_below: float) -> None:
    sharp, contrast = _ratios(worlds["fouling"], level)
    assert sharp < sharp_below and contrast > 0.9


@pytest.mark.parametrize(("level", "contrast_below"), [(0.5, 0.8), (0.75, 0.65), (1.0, 0.5)])
def test_turbidity_takes_contrast_and_leaves_sharpness(worlds: dict[str, World], level: float,
                                                       contrast_below: float) -> None:
    sharp, contrast = _ratios(worlds["turbidity"], level)
    assert contrast < contrast_below and sharp > 0.6


@pytest.mark.parametrize(("what", "state"), [("fouling", "fouled"), ("turbidity", "turbid"),
                                             ("clean", None)])
def test_flagged_within_an_hour_of_the_onset_with_the_defaults(
        worlds: dict[str, World], what: str, state: str | None) -> None:
    """The issue's bar: the watch with its default settings, one sample every 10 s of
    capture time, flags within an hour of the onset (and the clean floor never)."""
    cfg = ImageHealthConfig()
    watch = Watch(cfg)
    flagged = None
    for t in range(0, int(ONSET + RAMP), int(cfg.every_s)):
        change = watch.add(float(t), measure(worlds[what].render(t)[0], cfg.width))
        assert change is None or change.view.state in ("ok", state)
        if change is not None and change.view.state == state:
            flagged = t
            break
    if state is None:
        assert watch.view.state == "ok" and watch.view.changes == 0
    else:
        assert flagged is not None and flagged - ONSET < 3600


def test_animals_passing_never_flag() -> None:
    """A dense floor, an animal in every scene: the medians hold (windows scaled down with
    the sampling). The rig moving: tests/unit/test_synth_world.py, on its moving world."""
    cfg = ImageHealthConfig(every_s=5.0, baseline_s=60.0, window_s=40.0, hold_s=40.0)
    world = World(RIG, seed=5, moving=False, rate_hz=1.0,
                  options=SynthOptions(density=3.0, empty_fraction=0.0, episode_s=60.0))
    watch = Watch(cfg)
    seen = 0
    for t in range(0, 300, 5):
        left, _, truth = world.render(t)
        seen += bool(truth.objects)
        watch.add(float(t), measure(left, cfg.width))
        assert watch.view.state in ("learning", "ok")
    assert seen > 30 and watch.view.state == "ok"


# --- the shell, the health record and the status line -------------------------------------


def test_the_shell_keeps_its_baseline_and_logs_a_change_once(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    cfg = ImageHealthConfig(every_s=1.0, baseline_s=3.0, window_s=2.0, hold_s=2.0)
    world = World(RIG, seed=2, moving=False, rate_hz=1.0,
                  options=SynthOptions(density=0, snow=0, fouling_onset_s=10,
                                       fouling_ramp_s=0))
    shell = ImageWatch(cfg, tmp_path, RIG.size)
    caplog.set_level(logging.INFO, logger="trapflow.capture.image_watch")
    views = [shell.pair(world.render(t)[0], float(t)) for t in range(20)]
    assert all(v is not None for v in views) and shell.pair(world.render(0)[0], 19.5) is None
    assert (tmp_path / BASELINE_FILE).exists()
    assert views[-1] is not None and views[-1].state == "fouled"
    said = [r.getMessage() for r in caplog.records]
    assert sum("fouled (was ok)" in m for m in said) == 1
    assert sum("baseline learnt" in m for m in said) == 1
    # A capture restarted in the deployment compares with that baseline, not the fouled lens.
    again = ImageWatch(cfg, tmp_path, RIG.size)
    assert again.watch.baseline == shell.watch.baseline
    assert ImageWatch(cfg, tmp_path, (640, 480)).watch.baseline is None


def test_a_state_change_sends_a_health_record_at_once(tmp_path: Path) -> None:
    monitor = HealthMonitor(HealthConfig(interval_s=3600), tmp_path)
    assert monitor({}) is not None  # the first, due at once
    monitor.set_image(ImageHealth(state="ok", sharpness=1.0, contrast=1.0, brightness=1.0))
    assert monitor({}) is None  # a first view is no change
    fouled = ImageHealth(state="fouled", sharpness=0.314, contrast=1.02, brightness=0.9)
    monitor.set_image(fouled)
    record = monitor({})
    assert record is not None and monitor({}) is None
    body = record["health"]
    assert body["image"] == "fouled" and body["image_ratio"] == [0.31, 1.02, 0.9]
    data = LinkCodec().encode(record)
    assert data[0] == 5 and LinkCodec().decode(data)["health"]["image_ratio"] == [0.31, 1.02, 0.9]


def test_the_status_line_says_the_state_and_ratios() -> None:
    view = {"state": "turbid", "sharpness": 0.9, "contrast": 0.41, "brightness": 1.1,
            "samples": 400, "changes": 1}
    assert image_text(view) == ("image health: turbid; sharpness 0.90, contrast 0.41, "
                                "brightness 1.10 of the baseline; 400 samples, 1 changes")
    assert "12 samples" in image_text({**view, "state": "learning", "samples": 12})
