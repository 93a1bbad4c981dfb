"""The motion detector on synthetic frames: empty water with snow, a crab walking, light."""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import pytest

from trapflow.gate.motion import MotionConfig, MotionDetector, MotionResult

W, H = 640, 360
WARM = MotionConfig().warmup
CRAB = (70, 50)  # ellipse axes in pixels: a 10 cm crab at 1 m seen at 640 wide
Frame = Callable[[int, np.random.Generator], np.ndarray]


def sand(seed: int = 0) -> np.ndarray:
    """A textured sea floor, BGR, brighter in the middle (the lamp's pool of light)."""
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.normal(0, 25, (H, W)).astype(np.float32), (0, 0), 3)
    yy, xx = np.mgrid[0:H, 0:W]
    pool = 60 + 60 * np.exp(-(((xx - W / 2) / 300) ** 2 + ((yy - H / 2) / 200) ** 2))
    grey = np.clip(pool + tex, 0, 255).astype(np.uint8)
    out: np.ndarray = cv2.merge([grey, cv2.convertScaleAbs(grey, alpha=0.9), grey // 2])
    return out


FLOOR = sand()
TILTED = np.clip(FLOOR * np.linspace(0.4, 1.4, W)[None, :, None], 0, 255).astype(np.uint8)


def noisy(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    noise = rng.normal(0, 2.5, img.shape)
    out: np.ndarray = np.clip(img + noise, 0, 255).astype(np.uint8)
    return out


def snow(img: np.ndarray, rng: np.random.Generator, n: int = 150) -> np.ndarray:
    """Marine snow: n bright specks of 1-3 pixels radius, anywhere, new every frame."""
    out: np.ndarray = img.copy()
    for x, y, r in zip(rng.integers(0, W, n), rng.integers(0, H, n), rng.integers(1, 4, n),
                       strict=True):
        cv2.circle(out, (int(x), int(y)), int(r), (230, 230, 230), -1)
    return out


def crab_at(i: int) -> tuple[int, int]:
    """Centre of a crab walking left to right, 6 pixels a pair, after the warm-up."""
    return 100 + 6 * max(i - WARM, 0), 200


def with_crab(img: np.ndarray, i: int) -> np.ndarray:
    """The crab walks in once the background is built (one it was part of would leave a
    ghost where it stood)."""
    out: np.ndarray = img.copy()
    if i < WARM:
        return out
    cv2.ellipse(out, crab_at(i), (CRAB[0] // 2, CRAB[1] // 2), 0, 0, 360, (60, 110, 200), -1)
    return out


FRAMES: dict[str, Frame] = {
    "snow": lambda i, rng: snow(noisy(FLOOR, rng), rng),
    "heavy snow": lambda i, rng: snow(noisy(FLOOR, rng), rng, n=600),
    "flicker": lambda i, rng: cv2.convertScaleAbs(noisy(FLOOR, rng),
                                                  alpha=float(rng.uniform(0.9, 1.1))),
    "lamp dims": lambda i, rng: cv2.convertScaleAbs(noisy(FLOOR, rng),
                                                    alpha=0.6 if i >= WARM + 10 else 1.0),
    # The light tilts across the frame (a lamp fails on one side): not a uniform scale.
    "lamp shifts": lambda i, rng: noisy(FLOOR if i < WARM + 10 else TILTED, rng),
    "crab walks": lambda i, rng: noisy(with_crab(FLOOR, i), rng),
    "crab walks in snow": lambda i, rng: snow(noisy(with_crab(FLOOR, i), rng), rng),
}


def run(name: str, pairs: int, cfg: MotionConfig | None = None) -> list[MotionResult]:
    rng = np.random.default_rng(1)
    det = MotionDetector(cfg)
    return [det.update(FRAMES[name](i, rng)) for i in range(pairs)]


@pytest.mark.parametrize(("scene", "most_motion_pairs"), [
    ("snow", 0),  # specks a fraction of one small pixel each: never motion
    ("heavy snow", 0),  # four times as many specks: still none
    ("flicker", 0),  # +-10 % brightness every pair: the median normalisation cancels it
    ("lamp dims", 0),  # a uniform 40 % step: cancelled the same way
    ("lamp shifts", 1),  # the light moves across the frame: relearnt, at most one pair
])
def test_no_motion_without_an_animal(scene: str, most_motion_pairs: int) -> None:
    results = run(scene, WARM + 40)
    assert all(r.warming for r in results[:WARM])
    assert sum(r.motion for r in results[WARM:]) <= most_motion_pairs


@pytest.mark.parametrize("scene", [
    "crab walks",  # a crab on clean water
    "crab walks in snow",  # the same crab with snow all around it
])
def test_a_walking_crab_is_motion_with_a_region_over_it(scene: str) -> None:
    results = run(scene, WARM + 30)
    for i, r in enumerate(results[WARM:], start=WARM):
        assert r.motion, i
        x, y = crab_at(i)
        x1, y1, x2, y2 = r.regions[0]
        assert x1 <= x <= x2 and y1 <= y <= y2, (i, r.regions)
        assert len(r.regions) == 1 or scene.endswith("snow")
        assert 0 < r.score < 0.1


def test_lamp_shift_relearns_the_background() -> None:
    results = run("lamp shifts", WARM + 20)
    assert [r.relearnt for r in results].count(True) == 1


@pytest.mark.parametrize("method", ["mog2", "knn"])
def test_opencv_methods_see_the_crab_come(method: str) -> None:
    """OpenCV's subtractors share the clean-up; how long they keep seeing a walking crab
    (MOG2 learns it into its background within 3 pairs at alpha 0.05) and what snow does
    to them is compared by benchmarks/gate.py, not pinned here."""
    cfg = MotionConfig(method=method)
    assert all(r.motion for r in run("crab walks", WARM + 2, cfg)[WARM:])


def test_regions_in_full_frame_pixels_at_any_size() -> None:
    big = cv2.resize(with_crab(FLOOR, WARM + 10), (1280, 720))
    det = MotionDetector()
    for _ in range(WARM + 1):
        det.update(cv2.resize(FLOOR, (1280, 720)))
    x1, y1, x2, y2 = det.update(big).regions[0]
    x, y = crab_at(WARM + 10)
    assert x1 <= 2 * x <= x2 and y1 <= 2 * y <= y2


def test_grey_input_works_too() -> None:
    det = MotionDetector()
    grey = cv2.cvtColor(FLOOR, cv2.COLOR_BGR2GRAY)
    for _ in range(WARM + 1):
        assert not det.update(grey).motion
    assert det.update(cv2.cvtColor(with_crab(FLOOR, WARM + 5), cv2.COLOR_BGR2GRAY)).motion


@pytest.mark.parametrize(("kwargs", "error"), [
    ({"method": "optical_flow"}, "expected one of average, mog2, knn"),  # unknown method
    ({"width": 4}, "expected 8..640 x 8..480 pixels, got 4x45"),  # too small to see a crab
    ({"alpha": 0.01, "alpha_moving": 0.1}, "alpha_moving <= alpha"),  # inverted rates
    ({"min_area": 0}, "min_area >= 1"),  # a zero-pixel blob
    ({"max_cover": 0.0}, "0 < fraction <= 1"),  # everything would be light
    ({"samples": 17}, "expected 0..16 per side"),  # more than the 16x16 a small pixel covers
])
def test_config_rejects(kwargs: dict[str, object], error: str) -> None:
    with pytest.raises(ValueError, match=error):
        MotionConfig(**kwargs)  # type: ignore[arg-type]
