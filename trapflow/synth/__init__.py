"""The synthetic underwater stereo world: scene, animals, water, rendering, ground truth.

`World(rig, seed=..., moving=..., rate_hz=..., options=...)` renders pair i with
`render(i) -> (left, right, Truth)`; see trapflow.synth.render for the pose convention.
"""
