"""Example of a fifth algorithm: mean brightness of each image of the pair, as an Extra result.

One module plus one registry line (`"brightness": "trapflow_workers.example_brightness:Brightness"`)
or a pool with `plugin: trapflow_workers.example_brightness:Brightness`; docs/plugins.md explains.
"""

from __future__ import annotations

from typing import Annotated

import msgspec
import numpy as np

from trapflow.plugin import Context, Extra, Pair, Params, Worker, check_frame


class BrightnessParams(Params):
    """`pools.<pool>.params` of the example."""

    dark_below: Annotated[float, msgspec.Meta(ge=0, le=255)] = 40.0
    """Mean grey level under which the pair is reported as dark."""


class Brightness(Worker):
    """Reports mean left and right brightness and whether the scene is dark."""

    params_type = BrightnessParams  # the runtime validates `params:` into it

    def configure(self, params: BrightnessParams, ctx: Context) -> None:
        self.p = params

    def process(self, pair: Pair) -> Extra:
        check_frame(pair)
        left, right = float(np.mean(pair.left)), float(np.mean(pair.right))
        return Extra(
            name="brightness",
            fields={
                "left": round(left, 1),
                "right": round(right, 1),
                "dark": max(left, right) < self.p.dark_below,
            },
        )
