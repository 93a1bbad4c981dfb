"""The synthetic underwater world: renders stereo pairs with their ground truth.

Pose convention (what Truth.pose carries): the 3x4 [R|t] row-major transform
from the LEFT camera frame at this pair to the world frame, camera-to-world.
Camera frames follow OpenCV: x right, y down, z forward. The world frame is the
left camera frame of pair 0 (as in KITTI odometry poses), so pair 0 has the
identity pose and a static rig keeps it. The right camera sits baseline_m along
the left camera's +x. Rendering is true perspective: the floor (a textured
surface with geometric relief) is ray-cast per pixel on a coarse grid and
resampled, animals and boulders are planar sprites warped with their exact
homography, so disparity is correct everywhere.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from trapflow.calibration.camera import StereoRig
from trapflow.synth.animals import Placement, Population
from trapflow.synth.geometry import Trajectory, floor_points, inv_pose, right_of
from trapflow.synth.murk import Murk
from trapflow.synth.options import SynthOptions
from trapflow.synth.rays import Frustum, RayGrid
from trapflow.synth.sprites import Sprite, boulder, tag_sprite
from trapflow.synth.texture import Floor
from trapflow.synth.water import BACKSCATTER, F_SCALE, Light, Noise, Snow, to_u8
from trapflow.wire.messages import Truth, TruthObject

GRID = 4  # the floor is ray-cast every GRID pixels and resampled
LIGHT_GRID = 16  # a moving rig computes light and water every 16 pixels: they change slowly
TARGET_MEAN = 105.0  # auto exposure: mean grey level of the first left image
COUNT_VISIBLE = 0.35  # an animal at least this visible decides the scene label


@dataclass
class _Drawn:
    """A sprite as drawn in the left image, for occlusion bookkeeping."""

    place: Placement
    x0: int
    y0: int
    body: np.ndarray  # body mask over the clipped box


@dataclass
class _View:
    img: np.ndarray
    f8: np.ndarray
    b8: np.ndarray


class World:
    """A deterministic underwater scene seen by a stereo rig; render(i) gives pair i."""

    def __init__(self, rig: StereoRig, *, seed: int, moving: bool, rate_hz: float,
                 options: SynthOptions | None = None) -> None:
        self.rig, self.seed, self.rate_hz = rig, seed, rate_hz
        self.opts = opts = options or SynthOptions()
        rng = np.random.default_rng([seed, 1])
        self.traj = Trajectory(moving=moving, height_m=opts.height_m, tilt_deg=opts.tilt_deg,
                               speed=opts.speed, phase=float(rng.uniform(0, 2 * math.pi)))
        self.pose0 = self.traj.floor_pose(0.0)
        self.pose0_inv = inv_pose(self.pose0)
        w, h = rig.width, rig.height
        self._grid = RayGrid(rig, GRID)
        # A static rig lights its floor once, so it affords the fine grid.
        self._light_grid = RayGrid(rig, LIGHT_GRID) if moving else self._grid
        self._frustum = Frustum(rig)
        self.floor = Floor(*self._floor_bounds(), rng=rng)
        lo, hi = float(self.floor.geo.min()), float(self.floor.geo.max())
        self._mid_z, self._half_relief = (lo + hi) / 2.0, (hi - lo) / 2.0
        self.light = Light(rig, self._light_grid.us, self._light_grid.vs, opts.haze,
                           opts.light)
        self.boulders = self._place_boulders(np.random.default_rng([seed, 2]))
        self.tags = self._place_tags()
        occl = [(p.x, p.y, p.sprite.size_m * 0.4) for p in self.boulders]
        self.population = Population(seed, opts, self._inside, self._outside, occl)
        self.snow = Snow(opts.snow, np.random.default_rng([seed, 3]))
        self.noise = Noise(h, w, opts.noise, np.random.default_rng([seed, 4]))
        self.gain = 1.0
        probe = self._floor_view(self.pose0)
        self.gain = TARGET_MEAN / max(float(probe.img.mean()), 1.0)
        self.murk = Murk(opts, h, w, np.clip(BACKSCATTER * self.gain, 0, 255),
                         np.random.default_rng([seed, 6]))
        self._static: list[_View] | None = None
        self._sprite_cache: dict[tuple[int, int], tuple[int, int, np.ndarray, np.ndarray]] = {}
        self._contrib_cache: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self._lengths: dict[int, float] = {}  # sprites live as long as the world: ids stay valid
        if not moving:
            self._static = self._bake_static()

    # --- planning helpers ---------------------------------------------------------

    def _corner_points(self, pose: np.ndarray, margin: float) -> np.ndarray:
        w, h = self.rig.width, self.rig.height
        us = np.array([-margin * w, (1 + margin) * w, -margin * w, (1 + margin) * w])
        vs = np.array([-margin * h, -margin * h, (1 + margin) * h, (1 + margin) * h])
        pts = floor_points(self.rig, pose, us, vs)
        # Rays that miss the floor (near the horizon) count as far points.
        far = pose[:3, 3] + 6.0 * (pose[:3, :3] @ np.array([0.0, 0.0, 1.0]))
        pts = np.where(np.isnan(pts), far, pts)
        too_far = np.linalg.norm(pts - pose[:3, 3], axis=1) > 6.0
        pts[too_far] = far
        return pts

    def _floor_bounds(self) -> tuple[float, float, float, float]:
        pts = [self._corner_points(self.traj.floor_pose(t), 0.15)
               for t in self.traj.sample_times()]
        allp = np.concatenate(pts)
        m = 0.4
        return (float(allp[:, 0].min() - m), float(allp[:, 0].max() + m),
                float(allp[:, 1].min() - m), float(allp[:, 1].max() + m))

    def _inside(self, t: float, rng: np.random.Generator) -> np.ndarray:
        pose = self.traj.floor_pose(t)
        u = rng.uniform(0.1, 0.9) * self.rig.width
        v = rng.uniform(0.25, 0.85) * self.rig.height
        p = floor_points(self.rig, pose, np.array([u]), np.array([v]))[0]
        return np.asarray(p[:2]) if not np.isnan(p[0]) else np.asarray(pose[:2, 3])

    def _outside(self, t: float, rng: np.random.Generator) -> np.ndarray:
        pose = self.traj.floor_pose(t)
        w, h = self.rig.width, self.rig.height
        edge = int(rng.integers(3))
        if edge == 0:
            u, v = -0.2 * w, rng.uniform(0.3, 1.0) * h
        elif edge == 1:
            u, v = 1.2 * w, rng.uniform(0.3, 1.0) * h
        else:
            u, v = rng.uniform(0.1, 0.9) * w, 1.15 * h
        p = floor_points(self.rig, pose, np.array([u]), np.array([v]))[0]
        return np.asarray(p[:2]) if not np.isnan(p[0]) else np.asarray(pose[:2, 3])

    def _place_boulders(self, rng: np.random.Generator) -> list[Placement]:
        out = []
        if self.traj.moving:
            x0, x1, y0, y1 = self.floor.x0, self.floor.x0 + self.floor.wt * 0.002, \
                self.floor.y1 - self.floor.ht * 0.002, self.floor.y1
            n = int(rng.poisson(0.25 * (x1 - x0) * (y1 - y0)))
            spots = [np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)]) for _ in range(n)]
        else:
            spots = [self._inside(0.0, rng) for _ in range(int(rng.integers(1, 4)))]
        for i, p in enumerate(spots):
            dia = rng.uniform(0.12, 0.3)
            out.append(Placement(sprite=boulder(rng, dia), x=float(p[0]), y=float(p[1]),
                                 yaw=float(rng.uniform(0, 2 * math.pi)), lift=dia * 0.3,
                                 label="boulder", id=-(i + 1)))
        return out

    def _place_tags(self) -> list[Placement]:
        out = []
        rng = np.random.default_rng([self.seed, 5])
        n = self.opts.tags
        for i in range(n):
            u = (0.15 + 0.7 * (i % 4) / 3) * self.rig.width if n > 1 else 0.5 * self.rig.width
            v = (0.45 + 0.4 * (i // 4) / 3) * self.rig.height
            p = floor_points(self.rig, self.pose0, np.array([u]), np.array([v]))[0]
            out.append(Placement(sprite=tag_sprite(i, self.opts.tag_size_m), x=float(p[0]),
                                 y=float(p[1]), yaw=float(rng.uniform(-0.5, 0.5)), lift=0.003,
                                 label="tag", id=i))
        return out

    # --- rendering ------------------------------------------------------------------

    def _floor_view(self, pose: np.ndarray, right: bool = False,
                    dirs: np.ndarray | None = None) -> _View:
        """The lit floor seen from `pose`; dirs: the floor grid's rays rotated by the pose.

        Both cameras share their rotation, so render() rotates the rays once per pair.
        """
        floor_dirs = dirs if dirs is not None else self._grid.directions(pose[:3, :3])
        centre = pose[:3, 3]
        size = (self.rig.width, self.rig.height)
        t = self.floor.intersect(centre, floor_dirs)
        mx, my = (cv2.resize(m, size, interpolation=cv2.INTER_LINEAR)
                  for m in self.floor.texel_map(centre, floor_dirs, t))
        img4 = cv2.remap(self.floor.albedo4, mx, my, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT)
        img = cv2.cvtColor(img4, cv2.COLOR_BGRA2BGR)
        lg = self._light_grid
        if lg is not self._grid:
            # cv2.resize samples t at the light grid's cell centres, between floor-grid
            # cells: interpolated depth is all that the smooth lighting needs.
            t = cv2.resize(t, (lg.cols, lg.rows), interpolation=cv2.INTER_LINEAR)
        f, b = self.light.maps(t * lg.length, t, right, self.gain)
        f8 = cv2.resize(to_u8(f, F_SCALE), size, interpolation=cv2.INTER_LINEAR)
        b8 = cv2.resize(to_u8(b, 1.0), size, interpolation=cv2.INTER_LINEAR)
        img = cv2.multiply(img, f8, scale=1.0 / F_SCALE)
        cv2.add(img, b8, dst=img)
        return _View(img=img, f8=f8, b8=b8)

    def _homography(self, place: Placement, w2c: np.ndarray) -> np.ndarray:
        s = place.sprite
        m = s.size_m / s.side
        e1 = np.array([math.cos(place.yaw), math.sin(place.yaw), 0.0]) * m
        e2 = np.array([math.sin(place.yaw), -math.cos(place.yaw), 0.0]) * m
        z = float(self.floor.height_at(np.array([[place.x]]), np.array([[place.y]]))[0, 0])
        q = np.array([place.x, place.y, z + place.lift]) - (s.side - 1) / 2.0 * (e1 + e2)
        a = np.stack([w2c[:3, :3] @ e1, w2c[:3, :3] @ e2, w2c[:3, :3] @ q + w2c[:3, 3]], 1)
        out: np.ndarray = self.rig.K @ a
        return out

    def _warp(self, place: Placement, w2c: np.ndarray, view: int, cache_key: int | None
              ) -> tuple[int, int, np.ndarray, np.ndarray] | None:
        """The sprite warped into its clipped image box: (x0, y0, rgba, body)."""
        if cache_key is not None and (cache_key, view) in self._sprite_cache:
            return self._sprite_cache[(cache_key, view)]
        if self._surely_off_image(place, w2c):
            return None
        hm = self._homography(place, w2c)
        n = place.sprite.side
        corners = np.array([[0, 0, 1], [n - 1, 0, 1], [0, n - 1, 1], [n - 1, n - 1, 1]], float).T
        pc = hm @ corners
        if (pc[2] < 0.05).any():
            return None
        px, py = pc[0] / pc[2], pc[1] / pc[2]
        x0, y0 = max(int(math.floor(px.min())) - 1, 0), max(int(math.floor(py.min())) - 1, 0)
        x1 = min(int(math.ceil(px.max())) + 2, self.rig.width)
        y1 = min(int(math.ceil(py.max())) + 2, self.rig.height)
        if x1 <= x0 or y1 <= y0:
            return None
        shift = np.array([[1.0, 0, -x0], [0, 1.0, -y0], [0, 0, 1.0]]) @ hm
        size = (x1 - x0, y1 - y0)
        rgba = cv2.warpPerspective(place.sprite.rgba, shift, size, flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        body = cv2.warpPerspective(place.sprite.body, shift, size, flags=cv2.INTER_LINEAR,
                                   borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        out = (x0, y0, rgba, body)
        if cache_key is not None:
            self._sprite_cache[(cache_key, view)] = out
        return out

    def _surely_off_image(self, place: Placement, w2c: np.ndarray) -> bool:
        """A cheap test before the homography: most placements of a moving rig are out of view.

        The sprite lies within 0.71 x its side (half the diagonal) of its centre, and its
        centre within half the relief's range of the mid height.
        """
        centre = w2c[:3, :3] @ np.array([place.x, place.y, self._mid_z + place.lift]) + w2c[:3, 3]
        radius = 0.71 * place.sprite.size_m + self._half_relief
        return self._frustum.surely_outside(centre, radius)

    def _full_area(self, place: Placement, w2c: np.ndarray) -> float:
        """Projected area (px) of the sprite's body, unclipped: body fraction x quad area."""
        hm = self._homography(place, w2c)
        n = place.sprite.side
        corners = np.array([[0, 0, 1], [n - 1, 0, 1], [n - 1, n - 1, 1], [0, n - 1, 1]], float).T
        pc = hm @ corners
        quad = (pc[:2] / pc[2]).T.astype(np.float32)
        frac = float(place.sprite.body.mean())
        return abs(float(cv2.contourArea(quad))) * frac

    @staticmethod
    def _contribution(view: _View, x0: int, y0: int, rgba: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """What a sprite adds over its box (lit, through water), and its 3-channel alpha."""
        h, w = rgba.shape[:2]
        sl = (slice(y0, y0 + h), slice(x0, x0 + w))
        a = np.ascontiguousarray(rgba[..., 3])
        a3 = cv2.merge([a, a, a])
        rgb = cv2.cvtColor(rgba, cv2.COLOR_BGRA2BGR)  # 15x faster than a numpy channel slice
        contrib = cv2.multiply(rgb, view.f8[sl], dtype=cv2.CV_32F, scale=1.0 / F_SCALE)
        cv2.add(contrib, cv2.multiply(a3, view.b8[sl], dtype=cv2.CV_32F), dst=contrib)
        return contrib, a3

    @staticmethod
    def _blend(view: _View, x0: int, y0: int, contrib: np.ndarray, a3: np.ndarray) -> None:
        h, w = a3.shape[:2]
        sl = (slice(y0, y0 + h), slice(x0, x0 + w))
        keep = cv2.subtract(np.ones_like(a3), a3)
        out = cv2.multiply(view.img[sl], keep, dtype=cv2.CV_32F)
        cv2.add(out, contrib, dst=out)
        view.img[sl] = cv2.convertScaleAbs(out)

    def pose_at(self, index: int) -> np.ndarray:
        """4x4 left-camera-to-world pose of pair `index` (world = left camera of pair 0)."""
        out: np.ndarray = self.pose0_inv @ self.traj.floor_pose(index / self.rate_hz)
        return out

    def render(self, index: int) -> tuple[np.ndarray, np.ndarray, Truth]:
        """Pair `index` (at t = index / rate_hz): left, right BGR images and the truth."""
        t = index / self.rate_hz
        rng = np.random.default_rng([self.seed, 7, index])
        pose_l = self.traj.floor_pose(t)
        poses = [pose_l, right_of(pose_l, self.rig)]
        w2cs = [inv_pose(p) for p in poses]
        if self._static is not None:
            views = [_View(img=v.img.copy(), f8=v.f8, b8=v.b8) for v in self._static]
        else:
            dirs = self._grid.directions(pose_l[:3, :3])
            views = [self._floor_view(p, vi == 1, dirs) for vi, p in enumerate(poses)]
        static = self._static is not None
        animals = self.population.active(t)
        rot, trans = w2cs[0][:3, :3], w2cs[0][:3, 3]

        def depth(p: Placement) -> float:
            return float((rot @ np.array([p.x, p.y, 0.0]) + trans)[2])

        # Painter's order: flat tags first, then boulders and animals far to near. A static
        # rig has tags and boulders in its background already; a boulder is then only
        # redrawn over the animals behind it.
        order = ([] if static else list(self.tags)) + sorted(self.boulders + animals, key=depth,
                                                             reverse=True)
        drawn: list[_Drawn] = []
        rects: list[list[tuple[int, int, int, int]]] = [[], []]
        for place in order:
            fixed = static and place.label == "boulder"
            for vi, view in enumerate(views):
                got = self._warp(place, w2cs[vi], vi, id(place) if fixed else None)
                if got is None:
                    continue
                x0, y0, rgba, body = got
                if vi == 0:
                    drawn.append(_Drawn(place=place, x0=x0, y0=y0, body=body))
                if fixed:
                    self._redraw_over(view, vi, place, x0, y0, rgba, rects[vi])
                    continue
                contrib, a3 = self._contribution(view, x0, y0, rgba)
                self._blend(view, x0, y0, contrib, a3)
                rects[vi].append((x0, y0, x0 + rgba.shape[1], y0 + rgba.shape[0]))
        if static:
            drawn = [_Drawn(place=p, x0=g[0], y0=g[1], body=g[3]) for p in self.tags
                     if (g := self._warp(p, w2cs[0], 0, id(p))) is not None] + drawn
        truth_objects = self._truth_objects(drawn, w2cs[0])
        self._water_and_lens(views, index, pose_l, w2cs, rng)
        pose = np.round(self.pose0_inv @ pose_l, 12) + 0.0  # + 0.0: no negative zeros
        truth = Truth(seq=-1, pose=tuple(float(v) for v in pose[:3].reshape(-1)),
                      objects=truth_objects, scene_label=scene_label(truth_objects))
        return views[0].img, views[1].img, truth

    def _water_and_lens(self, views: list[_View], index: int, pose_l: np.ndarray,
                        w2cs: list[np.ndarray], rng: np.random.Generator) -> None:
        """Snow, motion blur, fouling and turbidity (before the sensor), then sensor noise."""
        t = index / self.rate_hz
        if self.opts.snow > 0:
            pts = self.snow.points(t, pose_l[:3, 3])
            colour = np.array([200.0, 215.0, 200.0]) * min(self.gain, 1.5)
            for vi, view in enumerate(views):
                self.snow.draw(view.img, self.rig, w2cs[vi], pts, colour)
        if self.opts.blur > 0:
            kernel = self._blur_kernel(index)
            for view in views:
                cv2.filter2D(view.img, -1, kernel, dst=view.img)
        if self.murk.enabled:
            self.murk.apply([v.img for v in views], t)
        for view in views:
            self.noise.apply(view.img, rng)

    def _blur_kernel(self, index: int) -> np.ndarray:
        """A line kernel along the image motion of the floor centre (horizontal if static)."""
        n = max(int(round(self.opts.blur)), 1)
        angle = 0.0
        if self.traj.moving:
            c = np.array([[self.rig.width / 2.0], [self.rig.height / 2.0]])
            a = self.pose_at(index)
            b = self.pose_at(index + 1)
            p = floor_points(self.rig, self.traj.floor_pose(index / self.rate_hz), c[0], c[1])[0]
            pw = self.pose0_inv @ np.append(p, 1.0)
            pa = inv_pose(a) @ pw
            pb = inv_pose(b) @ pw
            du = pb[0] / pb[2] - pa[0] / pa[2]
            dv = pb[1] / pb[2] - pa[1] / pa[2]
            angle = math.atan2(dv, du)
        k = np.zeros((2 * n + 1, 2 * n + 1), np.float32)
        end = (int(n + n * math.cos(angle)), int(n + n * math.sin(angle)))
        start = (int(n - n * math.cos(angle)), int(n - n * math.sin(angle)))
        cv2.line(k, start, end, 1.0, 1)
        out: np.ndarray = k / k.sum()
        return out

    def _redraw_over(self, view: _View, vi: int, place: Placement, x0: int, y0: int,
                     rgba: np.ndarray, rects: list[tuple[int, int, int, int]]) -> None:
        """Draw a static boulder again, only where animals behind it were drawn."""
        key = (id(place), vi)
        if key not in self._contrib_cache:
            base = self._static[vi] if self._static is not None else view
            self._contrib_cache[key] = self._contribution(base, x0, y0, rgba)
        contrib, a3 = self._contrib_cache[key]
        h, w = a3.shape[:2]
        for rx0, ry0, rx1, ry1 in rects:
            ix0, iy0 = max(rx0, x0), max(ry0, y0)
            ix1, iy1 = min(rx1, x0 + w), min(ry1, y0 + h)
            if ix1 <= ix0 or iy1 <= iy0:
                continue
            sub = (slice(iy0 - y0, iy1 - y0), slice(ix0 - x0, ix1 - x0))
            self._blend(view, ix0, iy0, np.ascontiguousarray(contrib[sub]),
                        np.ascontiguousarray(a3[sub]))

    def _bake_static(self) -> list[_View]:
        """Floor, tags and boulders of a static rig, drawn once per view."""
        views = []
        for vi, pose in enumerate((self.pose0, right_of(self.pose0, self.rig))):
            view = self._floor_view(pose, vi == 1)
            w2c = inv_pose(pose)
            rot, trans = w2c[:3, :3], w2c[:3, 3]
            far_first = sorted(self.boulders, reverse=True,
                               key=lambda p: float((rot @ np.array([p.x, p.y, 0.0]) + trans)[2]))
            for place in list(self.tags) + far_first:
                got = self._warp(place, w2c, vi, id(place))
                if got is not None:
                    contrib, a3 = self._contribution(view, got[0], got[1], got[2])
                    self._blend(view, got[0], got[1], contrib, a3)
            views.append(view)
        return views

    def _truth_objects(self, drawn: list[_Drawn], w2c: np.ndarray) -> list[TruthObject]:
        out = []
        for i, d in enumerate(drawn):
            if d.place.label not in ("crab", "scallop", "tag"):
                continue
            vis = d.body.copy()
            h, w = vis.shape
            for later in drawn[i + 1:]:
                if later.place.label == "tag":
                    continue
                ox0, oy0 = max(d.x0, later.x0), max(d.y0, later.y0)
                ox1 = min(d.x0 + w, later.x0 + later.body.shape[1])
                oy1 = min(d.y0 + h, later.y0 + later.body.shape[0])
                if ox1 <= ox0 or oy1 <= oy0:
                    continue
                vis[oy0 - d.y0:oy1 - d.y0, ox0 - d.x0:ox1 - d.x0] *= (
                    1.0 - later.body[oy0 - later.y0:oy1 - later.y0, ox0 - later.x0:ox1 - later.x0])
            seen = float(vis.sum())
            if seen < 4.0:
                continue
            full = max(self._full_area(d.place, w2c), seen)
            ys, xs = np.nonzero(d.body > 0.5)
            if len(xs) == 0:
                continue
            if d.place.label == "tag":
                box = self._tag_box(d.place, w2c)
            else:
                box = (float(d.x0 + xs.min()), float(d.y0 + ys.min()),
                       float(d.x0 + xs.max() + 1), float(d.y0 + ys.max() + 1))
            pc = w2c[:3, :3] @ np.array([d.place.x, d.place.y, 0.0]) + w2c[:3, 3]
            out.append(TruthObject(label=d.place.label, box=box, depth_m=round(float(pc[2]), 4),
                                   id=d.place.id, occluded=round(1.0 - seen / full, 3),
                                   length_m=0.0 if d.place.label == "tag" else
                                   round(self._length_m(d.place.sprite), 5),
                                   xyz=self._centre(d.place, w2c)))
        return out

    def _length_m(self, sprite: Sprite) -> float:
        """The body's greatest extent (its longest chord) in metres, once per sprite."""
        key = id(sprite)
        if key not in self._lengths:
            ys, xs = np.nonzero(sprite.body > 0.5)
            hull = cv2.convexHull(np.stack([xs, ys], 1).astype(np.float32)).reshape(-1, 2)
            chords = np.linalg.norm(hull[:, None, :] - hull[None, :, :], axis=2)
            # + 1: pixel centres span one pixel less than the body itself
            self._lengths[key] = (float(chords.max()) + 1.0) * sprite.size_m / sprite.side
        return self._lengths[key]

    def _centre(self, place: Placement, w2c: np.ndarray) -> tuple[float, float, float]:
        """The sprite's centre (on the floor, raised by its lift) in the left camera frame."""
        z = float(self.floor.height_at(np.array([[place.x]]), np.array([[place.y]]))[0, 0])
        pc = w2c[:3, :3] @ np.array([place.x, place.y, z + place.lift]) + w2c[:3, 3]
        return (round(float(pc[0]), 5), round(float(pc[1]), 5), round(float(pc[2]), 5))

    def _tag_box(self, place: Placement, w2c: np.ndarray) -> tuple[float, float, float, float]:
        hm = self._homography(place, w2c)
        n = place.sprite.side
        lo, hi = n * 0.1 - 0.5, n * 0.9 - 0.5  # the black square inside the white plate
        pc = hm @ np.array([[lo, lo, 1], [hi, lo, 1], [lo, hi, 1], [hi, hi, 1]], float).T
        px, py = pc[0] / pc[2], pc[1] / pc[2]
        w, h = self.rig.width, self.rig.height
        return (float(np.clip(px.min(), 0, w)), float(np.clip(py.min(), 0, h)),
                float(np.clip(px.max(), 0, w)), float(np.clip(py.max(), 0, h)))

    def tag_poses(self) -> dict[int, np.ndarray]:
        """4x4 tag-to-world poses (world = left camera of pair 0) of the floor's tags.

        Tag frame as the AprilTag C library's pose: origin at the centre, x to the right and
        y down of the tag as printed upright, z into the plate (down into the floor). The
        sprite draws OpenCV's marker, whose code is the printed tag turned 180 degrees.
        """
        out = {}
        for p in self.tags:
            z = float(self.floor.height_at(np.array([[p.x]]), np.array([[p.y]]))[0, 0]) + p.lift
            e1 = np.array([math.cos(p.yaw), math.sin(p.yaw), 0.0])
            up = -np.array([math.sin(p.yaw), -math.cos(p.yaw), 0.0])
            # OpenCV's marker frame (x right, y to its top, z up), turned 180 deg about y.
            r = np.stack([-e1, up, -np.cross(e1, up)], 1)
            m = np.eye(4)
            m[:3, :3], m[:3, 3] = r, [p.x, p.y, z]
            out[p.id] = self.pose0_inv @ m
        return out


def scene_label(objects: list[TruthObject]) -> str:
    """crab if a crab is at least 35% visible, else scallop likewise, else empty."""
    for label in ("crab", "scallop"):
        if any(o.label == label and o.occluded <= 1.0 - COUNT_VISIBLE for o in objects):
            return label
    return "empty"
