"""Who is on the floor and when: scenes (episodes) of crabs, scallops or nothing.

Each animal is a track: a pure function of time (position, heading, sprite), so
any frame can be rendered on its own and the same seed gives the same story.
Crabs walk in from an image edge sideways, pause, and walk out; scallops swim
in, sit (opening and closing) and swim off; empty stretches separate scenes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from trapflow.synth.options import SynthOptions
from trapflow.synth.sprites import CRAB_FRAMES, Sprite, crab_frames, scallop_pair

# (time, rng) -> floor point (x, y) inside the view or just beyond an edge of it.
Sampler = Callable[[float, np.random.Generator], np.ndarray]
GAP_S = (1.0, 3.0)  # empty time between scenes


@dataclass
class Placement:
    """Where a sprite is at one instant: floor position, yaw, lift above the floor."""

    sprite: Sprite
    x: float
    y: float
    yaw: float
    lift: float
    label: str
    id: int


@dataclass
class Track:
    """One animal's visit: waypoints with times, and how it looks."""

    kind: str
    id: int
    sprites: list[Sprite]
    times: np.ndarray  # (N,) seconds
    points: np.ndarray  # (N, 2) floor xy
    yaws: np.ndarray  # (N,) yaw while on the segment that starts at each waypoint
    lift: float
    stride_m: float = 0.05
    period_s: float = 6.0
    phase: float = 0.0

    @property
    def t_in(self) -> float:
        return float(self.times[0])

    @property
    def t_out(self) -> float:
        return float(self.times[-1])

    def at(self, t: float) -> Placement | None:
        if not self.t_in <= t <= self.t_out:
            return None
        x = float(np.interp(t, self.times, self.points[:, 0]))
        y = float(np.interp(t, self.times, self.points[:, 1]))
        seg = min(int(np.searchsorted(self.times, t, side="right")) - 1, len(self.yaws) - 1)
        yaw = float(self.yaws[max(seg, 0)])
        lift = self.lift
        if self.kind == "crab":
            steps = np.hypot(*np.diff(self.points, axis=0).T)
            walked = float(np.interp(t, self.times, np.concatenate([[0.0], np.cumsum(steps)])))
            sprite = self.sprites[int(walked / self.stride_m * CRAB_FRAMES) % CRAB_FRAMES]
        else:
            swim = 1.2
            if t - self.t_in < swim or self.t_out - t < swim:  # swimming: raised, clapping
                edge = min(t - self.t_in, self.t_out - t) / swim
                lift += 0.12 * math.sin(math.pi * (1.0 - edge) / 2.0) ** 2
                opened = int(t * 4.0) % 2 == 0
            else:
                opened = math.sin(2 * math.pi * t / self.period_s + self.phase) > -0.3
            sprite = self.sprites[1 if opened else 0]
        return Placement(sprite=sprite, x=x, y=y, yaw=yaw, lift=lift, label=self.kind, id=self.id)


def _front_yaw(dx: float, dy: float, sign: float) -> float:
    """Yaw pointing a sprite's top (the animal's front) across the motion: crabs walk sideways."""
    fx, fy = -dy * sign, dx * sign
    return math.atan2(-fx, fy)


class Population:
    """Generates scenes lazily as time advances; deterministic from the seed."""

    def __init__(self, seed: int, opts: SynthOptions, inside: Sampler, outside: Sampler,
                 occluders: list[tuple[float, float, float]]) -> None:
        self.seed, self.opts = seed, opts
        self.inside, self.outside = inside, outside
        self.occluders = occluders  # boulders (x, y, radius): crabs sometimes pause behind
        self.tracks: list[Track] = []
        self.scenes: list[tuple[float, float, str]] = []  # start, end, kind
        self._next_start = 0.0
        self._next_id = 0

    def active(self, t: float) -> list[Placement]:
        """Every animal on the floor at time t."""
        while self._next_start <= t + 1.0:
            self._plan_scene(len(self.scenes))
        out = []
        for tr in self.tracks:
            if tr.t_in <= t <= tr.t_out:
                p = tr.at(t)
                if p is not None:
                    out.append(p)
        return out

    def _plan_scene(self, k: int) -> None:
        rng = np.random.default_rng([self.seed, 101, k])
        start = self._next_start
        dur = self.opts.episode_s * rng.uniform(0.5, 1.5)
        if self.opts.density <= 0 or rng.random() < self.opts.empty_fraction:
            kind = "empty"
        else:
            kind = "crab" if rng.random() < 0.5 else "scallop"
        end = start + dur
        if kind == "crab":
            n = min(1 + int(rng.poisson(0.8 * self.opts.density)), 5)
            for _ in range(n):
                end = max(end, self._plan_crab(start, dur, rng))
        elif kind == "scallop":
            n = min(1 + int(rng.poisson(1.5 * self.opts.density)), 7)
            for _ in range(n):
                end = max(end, self._plan_scallop(start, dur, rng))
        self.scenes.append((start, end, kind))
        self._next_start = end + rng.uniform(*GAP_S)

    def _new_id(self) -> int:
        self._next_id += 1
        return self._next_id

    def _plan_crab(self, start: float, dur: float, rng: np.random.Generator) -> float:
        t = start + rng.uniform(0.0, 0.35) * dur
        speed = rng.uniform(0.05, 0.14)
        carapace = rng.uniform(0.06, 0.16)
        sign = 1.0 if rng.random() < 0.5 else -1.0
        times, points, yaws = [t], [self.outside(t + 2.0, rng)], []
        stops = int(rng.integers(1, 3))
        for i in range(stops + 1):
            ahead = t + 3.0  # a moving rig: aim where the view will be on arrival
            if i == stops:
                nxt = self.outside(ahead, rng)
            elif self.occluders and rng.random() < 0.35:  # stop by a boulder, partly hidden
                bx, by, br = self.occluders[int(rng.integers(len(self.occluders)))]
                a = rng.uniform(0, 2 * math.pi)
                nxt = np.array([bx + br * 0.9 * math.cos(a), by + br * 0.9 * math.sin(a)])
            else:
                nxt = self.inside(ahead, rng)
            d = nxt - points[-1]
            yaw = _front_yaw(float(d[0]), float(d[1]), sign)
            t += float(np.hypot(*d)) / speed
            yaws.append(yaw)
            times.append(t)
            points.append(nxt)
            if i < stops:  # pause
                t += rng.uniform(0.5, 4.0)
                yaws.append(yaw)
                times.append(t)
                points.append(nxt)
        yaws.append(yaws[-1])
        frames = crab_frames(rng, carapace)
        self.tracks.append(Track(kind="crab", id=self._new_id(), sprites=frames,
                                 times=np.array(times), points=np.array(points),
                                 yaws=np.array(yaws), lift=carapace * 0.25,
                                 stride_m=carapace * 0.6))
        return t

    def _plan_scallop(self, start: float, dur: float, rng: np.random.Generator) -> float:
        t0 = start + rng.uniform(0.0, 0.3) * dur
        t1 = start + dur * rng.uniform(0.7, 1.0)
        home = self.inside(t0, rng)
        src, dst = self.outside(t0, rng), self.outside(t1, rng)
        # Swim in and out quickly from and to just beyond the view.
        frac = 0.35  # only the last part of the swim is shown, the scallop lands in view
        entry = home + (src - home) * frac
        leave = home + (dst - home) * frac
        yaw = rng.uniform(0, 2 * math.pi)
        diameter = rng.uniform(0.07, 0.13)
        closed, opened = scallop_pair(rng, diameter)
        times = np.array([t0, t0 + 1.2, t1 - 1.2, t1])
        points = np.array([entry, home, home, leave])
        self.tracks.append(Track(kind="scallop", id=self._new_id(), sprites=[closed, opened],
                                 times=times, points=points, yaws=np.full(4, yaw),
                                 lift=diameter * 0.12, period_s=rng.uniform(4.0, 12.0),
                                 phase=rng.uniform(0, 2 * math.pi)))
        return t1
