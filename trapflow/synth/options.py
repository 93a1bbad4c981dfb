"""Options of the synthetic world (`source.options`), validated with errors naming the key."""

from __future__ import annotations

from typing import Annotated, Any

import msgspec

from trapflow.errors import ConfigError


class SynthOptions(msgspec.Struct, kw_only=True, forbid_unknown_fields=True, frozen=True):
    """Knobs of the synthetic underwater world; every one has a sensible default."""

    density: Annotated[float, msgspec.Meta(ge=0, le=5)] = 1.0
    """Scale of the number of animals per scene (0: never any animal)."""
    empty_fraction: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.3
    """Share of scenes (episodes) with no animal at all."""
    episode_s: Annotated[float, msgspec.Meta(ge=2, le=600)] = 20.0
    """Mean duration of one scene (episode) in seconds."""
    snow: Annotated[float, msgspec.Meta(ge=0, le=5)] = 1.0
    """Marine snow density (0 switches it off)."""
    blur: Annotated[float, msgspec.Meta(ge=0, le=30)] = 0.0
    """Motion blur length in pixels (0 switches it off)."""
    noise: Annotated[float, msgspec.Meta(ge=0, le=30)] = 2.5
    """Sensor noise standard deviation in grey levels."""
    haze: Annotated[float, msgspec.Meta(ge=0, le=5)] = 1.0
    """Turbidity: scales attenuation and backscatter (0: clear air)."""
    light: Annotated[float, msgspec.Meta(ge=0, le=3)] = 1.0
    """Strength of the trap's lamp relative to daylight."""
    height_m: Annotated[float, msgspec.Meta(ge=0.3, le=3)] = 0.9
    """Height of the left camera above the mean sea floor."""
    tilt_deg: Annotated[float, msgspec.Meta(ge=35, le=90)] = 45.0
    """Downward tilt of the cameras below the horizontal (90: straight down)."""
    speed: Annotated[float, msgspec.Meta(gt=0, le=2)] = 0.15
    """Moving mode: mean speed of the rig along its trajectory, m/s."""
    tags: Annotated[int, msgspec.Meta(ge=0, le=16)] = 0
    """Number of AprilTag 36h11 markers laid on the floor (ids 0..tags-1)."""
    tag_size_m: Annotated[float, msgspec.Meta(ge=0.03, le=0.5)] = 0.12
    """Side of a tag's black square in metres."""
    # The lens and the water over a deployment (trapflow.synth.murk), by the world's time
    # t = pair index / rate_hz: off (null onset) unless asked, so the default world is as it was.
    fouling_onset_s: Annotated[float, msgspec.Meta(ge=0)] | None = None
    """World time (s) at which the ports start to foul (null: never)."""
    fouling_ramp_s: Annotated[float, msgspec.Meta(ge=0, le=1e7)] = 3600.0
    """Seconds from the fouling's onset to its full extent (0: at once)."""
    fouling_blur_px: Annotated[float, msgspec.Meta(ge=0, le=40)] = 6.0
    """Blur (Gaussian sigma, pixels) of a fully fouled port where its growth is thickest."""
    fouling_cover: Annotated[float, msgspec.Meta(ge=0, le=1)] = 0.6
    """Light a fully fouled port loses where its growth is thickest (0..1); uneven over the
    image, as silt and growth are."""
    turbidity_onset_s: Annotated[float, msgspec.Meta(ge=0)] | None = None
    """World time (s) at which the water starts to turn turbid (null: never)."""
    turbidity_ramp_s: Annotated[float, msgspec.Meta(ge=0, le=1e7)] = 3600.0
    """Seconds from the turbidity's onset to its full extent (0: at once)."""
    turbidity_veil: Annotated[float, msgspec.Meta(ge=0, le=0.95)] = 0.6
    """Share of the image's light replaced by the water's colour at full turbidity (haze)."""


def parse_options(data: Any, prefix: str = "source.options") -> SynthOptions:
    """Validate a plain dict into SynthOptions; ConfigError names `source.options.<key>`."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix}: expected a mapping of option names to values, got {data!r}")
    known = set(SynthOptions.__struct_fields__)
    for key in data:
        if key not in known:
            raise ConfigError(
                f"{prefix}.{key}: unknown option of the synthetic source; "
                f"expected one of {', '.join(sorted(known))}"
            )
    try:
        return msgspec.convert(data, SynthOptions, strict=True)
    except msgspec.ValidationError as exc:
        text = str(exc)
        key = text.rpartition("- at `$.")[2].rstrip("`") if "- at `$." in text else ""
        what = text.partition(" - at ")[0]
        got = data.get(key, "?") if key else data
        raise ConfigError(f"{prefix}.{key}: {what}, got {got!r}") from None
