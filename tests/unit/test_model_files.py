"""The demo models committed in workers/models stay small enough to ship in the package
(their accuracy on held-out scenes: tests/integration/test_synth_models.py)."""

from __future__ import annotations

from pathlib import Path

MODELS = Path(__file__).resolve().parents[2] / "workers" / "models"


def test_models_are_small() -> None:
    models = list(MODELS.glob("*.onnx"))
    assert models, f"no ONNX model in {MODELS}"
    for path in models:
        assert path.stat().st_size < 5 * 1024 * 1024, path.name
