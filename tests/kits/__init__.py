"""Builders the tests and benchmarks share: plugin contexts, tiny ONNX models, exact scenes."""
