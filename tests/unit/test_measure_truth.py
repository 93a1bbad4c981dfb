"""The synthetic truth's length and position of each animal, and the wire without them."""

from __future__ import annotations

import msgspec
import pytest

from trapflow.calibration.camera import StereoRig
from trapflow.synth.options import SynthOptions
from trapflow.synth.render import World
from trapflow.wire.messages import TruthObject

RIG = StereoRig.from_fov(640, 360, 70.0, 0.12)


@pytest.mark.timeout(60)
def test_animal_centre_projects_into_its_box_and_length_is_its_size() -> None:
    world = World(RIG, seed=5, moving=False, rate_hz=10.0,
                  options=SynthOptions(density=2.0, empty_fraction=0.0))
    _, _, truth = world.render(50)
    animals = [o for o in truth.objects if o.label in ("crab", "scallop")]
    assert animals
    for o in animals:
        assert o.xyz is not None
        x, y, z = o.xyz
        u, v = RIG.fx * x / z + RIG.cx, RIG.fy * y / z + RIG.cy
        x1, y1, x2, y2 = o.box
        assert x1 <= u <= x2 and y1 <= v <= y2
        # the box's width at the centre's depth cannot exceed the body's longest chord much
        assert (x2 - x1) * z / RIG.fx <= o.length_m * 1.1
        assert 0.05 < o.length_m < 0.5


def test_unset_fields_stay_off_the_wire() -> None:
    """An old reader sees the same bytes for an object without length and position."""
    plain = TruthObject(label="crab", box=(1.0, 2.0, 3.0, 4.0))
    assert b"length_m" not in msgspec.json.encode(plain)
    assert b"xyz" not in msgspec.json.encode(plain)
