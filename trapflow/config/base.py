"""The base of every config section: a Struct that rejects unknown keys, and the number types
the sections share."""

from __future__ import annotations

from typing import Annotated

import msgspec


class Section(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """A config section: keyword-only, unknown keys rejected with their YAML path."""


Positive = Annotated[float, msgspec.Meta(gt=0)]
