"""What a month does to the view: fouling on the ports and turbid water, by the world's time.

Both ramp linearly from their onset (SynthOptions.fouling_onset_s, turbidity_onset_s) to
full over their ramp, and are off unless an onset is set (the default world is untouched).

- Turbidity (in the water, the same for both cameras): a share v of each pixel's light is
  replaced by the water's colour (the backscatter's), and a little forward scatter softens
  the image: contrast falls, the image goes toward the water colour.
- Fouling (on each port, its own pattern): a smooth random field says where growth and silt
  are thickest; there the image is blurred most (up to fouling_blur_px) and loses most light
  (up to fouling_cover). Uneven, as real fouling is.

Both act on the image through the lens, before the sensor's noise (which no fouling blurs).
`level(t)` of each is the truth a detector is scored against.
"""

from __future__ import annotations

import cv2
import numpy as np

from trapflow.synth.options import SynthOptions

FIELD_CELLS = (4, 3)  # the fouling pattern's coarse grid (x, y): a few patches per port
FORWARD_SCATTER_PX = 1.0  # blur (sigma) of full turbidity at a veil of 1


def ramp(t: float, onset: float | None, ramp_s: float) -> float:
    """0 before the onset (or without one), rising linearly to 1 over ramp_s."""
    if onset is None or t < onset:
        return 0.0
    if ramp_s <= 0:
        return 1.0
    return min((t - onset) / ramp_s, 1.0)


class Murk:
    """Applies fouling and turbidity of the world's time to a rendered pair, in place."""

    def __init__(self, opts: SynthOptions, height: int, width: int, water: np.ndarray,
                 rng: np.random.Generator) -> None:
        self.opts = opts
        self.water = water.astype(np.float32)  # BGR grey levels the veil tends to
        self.fields = [self._field(height, width, rng) for _ in range(2)]

    @property
    def enabled(self) -> bool:
        o = self.opts
        return o.fouling_onset_s is not None or o.turbidity_onset_s is not None

    def fouling(self, t: float) -> float:
        """The ports' fouling at world time t, 0..1 of its full extent."""
        return ramp(t, self.opts.fouling_onset_s, self.opts.fouling_ramp_s)

    def turbidity(self, t: float) -> float:
        """The water's turbidity at world time t, 0..1 of its full extent."""
        return ramp(t, self.opts.turbidity_onset_s, self.opts.turbidity_ramp_s)

    @staticmethod
    def _field(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
        """A smooth field in 0..1 (1 where the growth is thickest), HxWx1 float32."""
        coarse = rng.random((FIELD_CELLS[1], FIELD_CELLS[0])).astype(np.float32)
        f = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
        lo, hi = float(f.min()), float(f.max())
        out: np.ndarray = ((f - lo) / max(hi - lo, 1e-6)).astype(np.float32)[..., None]
        return out

    def apply(self, images: list[np.ndarray], t: float) -> None:
        """Turbidity, then fouling, of time t on each image (left, right) in place."""
        veil = self.turbidity(t) * self.opts.turbidity_veil
        foul = self.fouling(t)
        for side, img in enumerate(images):
            if veil > 0:
                self._veil(img, veil)
            if foul > 0:
                self._foul(img, foul, self.fields[side])

    def _veil(self, img: np.ndarray, v: float) -> None:
        sigma = FORWARD_SCATTER_PX * v
        src = cv2.GaussianBlur(img, (0, 0), sigma) if sigma >= 0.3 else img
        out = cv2.addWeighted(src.astype(np.float32), 1.0 - v,
                              np.broadcast_to(self.water, img.shape).astype(np.float32), v, 0.0)
        img[:] = np.clip(out + 0.5, 0, 255).astype(np.uint8)

    def _foul(self, img: np.ndarray, level: float, field: np.ndarray) -> None:
        o = self.opts
        sigma = o.fouling_blur_px * level
        f = img.astype(np.float32)
        if sigma >= 0.3:
            # Blurred everywhere a little, most where the growth is thickest.
            weight = np.minimum(level * (0.5 + field), 1.0)
            blurred = cv2.GaussianBlur(f, (0, 0), sigma)
            f = f + (blurred - f) * weight
        f *= 1.0 - o.fouling_cover * level * field * field
        img[:] = np.clip(f + 0.5, 0, 255).astype(np.uint8)
