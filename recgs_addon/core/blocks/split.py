"""A survey split into blocks over the seabed (VastGaussian's design, for a 2.5D seabed).

The seabed plane is fitted to the sparse points; its first axis runs along their longest
spread. The plane is cut into ``n`` cells: columns along that axis, each cut into rows across
it, at quantiles of the cameras' footprint centres so that every block gets about as many
photos as every other (a block's training time is shared among its photos). Each block trains
on every photo that sees its cell grown by a margin (visibility from the sparse points: the
share of a photo's visible points that fall in the grown cell), starts from the sparse points
in the grown cell, and keeps, when the blocks are merged, only the Gaussians inside its own cell.

The survey's held-out photos are held out of every block: each is scored, in its block, by the
block whose cell holds its footprint's centre, and the merged scene is scored on all of them.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import RecGSError
from ..io.colmap import Scene
from ..model.cells import EDGE, Cell

#: A photo trains a block when at least this share of the sparse points it sees lie in the
#: block's grown cell (VastGaussian keeps a camera whose view of the cell covers a quarter of it).
MIN_SHARE = 0.25
#: The margin a cell is grown by for the photos and points a block trains on, as a share of the
#: cell's shorter side (VastGaussian grows its cells by 20 %).
MARGIN = 0.2
#: A block needs at least this many training photos.
MIN_BLOCK_VIEWS = 3
#: A held-out photo crosses a seam when less than this share of what it sees is in one cell.
SEAM_SHARE = 0.9
#: Sparse points used for visibility at most (a uniform sample beyond).
VISIBILITY_POINTS = 20_000
#: Blocks on which a training photo trains on average beyond which a split is refused on one
#: machine: the blocks share its cores, so at equal compute each photo gets this many times
#: fewer steps than in one job (a 64-photo survey a few footprints wide in 4 blocks: 3.3, and
#: 37.71 dB against one job's 39.77).
MAX_DUPLICATION = 2.0
#: ... and beyond which the plan warns.
WARN_DUPLICATION = 1.5


@dataclass
class Block:
    name: str
    cell: Cell               # where its Gaussians are kept
    grown: Cell              # where its photos look and its sparse points start
    train: list[str]         # photos it trains on
    test: list[str]          # the survey's held-out photos it is scored on
    points: int = 0          # sparse points it starts from

    def config(self) -> dict:
        """``TrainConfig.block``: what the trainer needs of the block."""
        return {"name": self.name, "train": list(self.train), "test": list(self.test), "cell": self.grown.to_dict()}

    def to_dict(self) -> dict:
        return {"name": self.name, "cell": self.cell.to_dict(), "grown": self.grown.to_dict(),
                "train": list(self.train), "test": list(self.test), "points": self.points}

    @classmethod
    def from_dict(cls, d: dict) -> "Block":
        return cls(d["name"], Cell.from_dict(d["cell"]), Cell.from_dict(d["grown"]), list(d["train"]),
                   list(d["test"]), int(d.get("points", 0)))


@dataclass
class BlockPlan:
    """The blocks of one survey, and what the split saw."""
    blocks: list[Block]
    grid: tuple                      # (columns, rows)
    margin: float                    # scene units
    test: list[str]                  # the survey's held-out photos
    seam_views: list[str] = field(default_factory=list)   # held-out photos that cross a seam
    owner: dict = field(default_factory=dict)              # photo -> the block whose cell holds its footprint's centre

    def to_dict(self) -> dict:
        return {"grid": list(self.grid), "margin": self.margin, "test": self.test, "seam_views": self.seam_views,
                "owner": self.owner, "blocks": [b.to_dict() for b in self.blocks]}

    @classmethod
    def from_dict(cls, d: dict) -> "BlockPlan":
        return cls([Block.from_dict(b) for b in d["blocks"]], tuple(d["grid"]), float(d["margin"]), list(d["test"]),
                   list(d.get("seam_views", [])), dict(d.get("owner", {})))

    def save(self, path: Path) -> None:
        from ..io.atomic import atomic_path

        with atomic_path(path, "block plan") as tmp:
            Path(tmp).write_text(json.dumps(self.to_dict(), indent=1))

    @classmethod
    def load(cls, path: Path) -> "BlockPlan":
        try:
            return cls.from_dict(json.loads(Path(path).read_text()))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise RecGSError(f"{path}: not a block plan this version reads ({exc})") from exc

    @property
    def duplication(self) -> float:
        """Blocks a training photo trains in, on average (1: every photo in one block)."""
        unique = {name for b in self.blocks for name in b.train}
        return sum(len(b.train) for b in self.blocks) / max(len(unique), 1)

    def cost_line(self) -> str:
        """What the blocks cost in duplicated photos."""
        d = self.duplication
        line = (f"each training photo trains in {d:.2f} blocks on average: on the same cores each photo gets "
                f"{1 / d:.2f} of one job's steps")
        if d > WARN_DUPLICATION:
            line += ("; the survey is small for this many blocks (they pay where one job does not fit in memory, "
                     "or on more machines)")
        return line

    def lines(self) -> list[str]:
        lines = [f"blocks: {len(self.blocks)} ({self.grid[0]} x {self.grid[1]} over the seabed), margin "
                 f"{self.margin:.3g}; {len(self.seam_views)} of {len(self.test)} held-out photos cross a seam",
                 self.cost_line()]
        for b in self.blocks:
            lines.append(f"  {b.name}: {len(b.train)} photos, {len(b.test)} held out, {b.points} sparse points")
        return lines


def seabed_axes(points: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin, u, v): the plane through the sparse points (their centre, the two directions of
    largest spread, u the longer), from the cameras' centres where the points are too few."""
    pts = points if len(points) >= 3 else centres
    pts = np.asarray(pts, dtype=np.float64)
    origin = np.median(pts, axis=0)
    if len(pts) > 50_000:
        pts = pts[np.random.default_rng(0).choice(len(pts), 50_000, replace=False)]
    _, _, vt = np.linalg.svd(pts - origin, full_matrices=False)
    u = vt[0] if len(vt) > 0 else np.array([1.0, 0.0, 0.0])
    v = vt[1] if len(vt) > 1 else np.cross([0.0, 0.0, 1.0], u)
    if np.linalg.norm(v) < 1e-9:
        v = np.cross([0.0, 1.0, 0.0], u)
    v = v - u * (u @ v)
    return origin, u / np.linalg.norm(u), v / np.linalg.norm(v)


def visibility(scene: Scene, points: np.ndarray) -> list[np.ndarray]:
    """For each camera, the indices of ``points`` in front of it and inside its image (occlusion
    is not tested: on a 2.5D seabed the frustum is what a photo sees)."""
    out = []
    for cam in scene.cameras:
        pc = points @ np.asarray(cam.R, dtype=np.float64).T + np.asarray(cam.t, dtype=np.float64)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = cam.fx * pc[:, 0] / z + cam.cx
            y = cam.fy * pc[:, 1] / z + cam.cy
        out.append(np.flatnonzero((z > 1e-6) & (x >= 0) & (x < cam.width) & (y >= 0) & (y < cam.height)))
    return out


def _grid(n: int, extent_u: float, extent_v: float) -> tuple[int, int]:
    """(columns, rows), columns * rows = n, whose cells are closest to square."""
    best = None
    for cols in range(1, n + 1):
        if n % cols:
            continue
        rows = n // cols
        cost = abs(math.log(max(extent_u / cols, 1e-12) / max(extent_v / rows, 1e-12)))
        if best is None or cost < best[0]:
            best = (cost, cols, rows)
    return best[1], best[2]


def _cuts(values: np.ndarray, parts: int) -> list[float]:
    """``parts + 1`` boundaries: -EDGE, the quantiles that cut ``values`` into equal parts, EDGE."""
    inner = [float(np.quantile(values, k / parts)) for k in range(1, parts)] if len(values) else [0.0] * (parts - 1)
    return [-EDGE, *inner, EDGE]


@dataclass
class SplitGeometry:
    """What every split of one survey shares, whatever the count: the seabed plane, the sparse
    points (a sample) on it, what each photo sees and its footprint's centre, the points' extent."""
    origin: tuple
    axes: tuple
    uv: np.ndarray          # (P, 2) the points on the plane
    seen: list              # per photo, the indices of the points it sees
    foot: np.ndarray        # (photos, 2) footprint centres on the plane
    lo: np.ndarray
    hi: np.ndarray


def split_geometry(scene: Scene) -> SplitGeometry:
    """:class:`SplitGeometry` of ``scene`` (the visibility test is the costly part: made once for
    any number of splits tried)."""
    centres = np.stack([np.asarray(c.center, dtype=np.float64) for c in scene.cameras])
    pts = np.asarray(scene.points, dtype=np.float64)
    if len(pts) > VISIBILITY_POINTS:
        pts = pts[np.random.default_rng(0).choice(len(pts), VISIBILITY_POINTS, replace=False)]
    origin, u, v = seabed_axes(pts, centres)
    axes = (tuple(u), tuple(v))
    plane = Cell(tuple(origin), axes, (-EDGE, EDGE, -EDGE, EDGE))
    uv = plane.plane_coords(pts)
    seen = visibility(scene, pts)
    # a photo's footprint centre: the median of the points it sees (its centre projected if none)
    foot = np.stack([np.median(uv[s], axis=0) if len(s) else plane.plane_coords(centres[i:i + 1])[0]
                     for i, s in enumerate(seen)])
    lo, hi = np.percentile(uv, [2, 98], axis=0) if len(uv) else (foot.min(0), foot.max(0))
    return SplitGeometry(tuple(origin), axes, uv, seen, foot, lo, hi)


def plan_blocks(scene: Scene, n: int, test: list[str], min_share: float = MIN_SHARE,
                margin: float = MARGIN, geometry: Optional[SplitGeometry] = None) -> BlockPlan:
    """Split ``scene`` into ``n`` blocks (see the module's docstring); ``test``: the survey's
    held-out photos by name; ``geometry``: the survey's :func:`split_geometry`, where it is made
    already. Refuses (RecGSError) a split that leaves a block too few photos."""
    if n < 2:
        raise RecGSError(f"--blocks must be 2 or more to split a survey, got {n}")
    names = [c.name for c in scene.cameras]
    g = geometry if geometry is not None else split_geometry(scene)
    origin, axes, uv, seen, foot, lo, hi = g.origin, g.axes, g.uv, g.seen, g.foot, g.lo, g.hi
    cols, rows = _grid(n, hi[0] - lo[0], hi[1] - lo[1])
    cells = []
    ucut = _cuts(foot[:, 0], cols)
    for c in range(cols):
        in_col = (foot[:, 0] >= ucut[c]) & (foot[:, 0] < ucut[c + 1])
        vcut = _cuts(foot[in_col, 1], rows)
        cells += [Cell(origin, axes, (ucut[c], ucut[c + 1], vcut[r], vcut[r + 1])) for r in range(rows)]
    # the margin: a share of the cells' shorter side, the outer sides taken at the points' extent
    sides = []
    for cell in cells:
        u0, u1, v0, v1 = cell.bounds
        sides.append(min(min(u1, hi[0]) - max(u0, lo[0]), min(v1, hi[1]) - max(v0, lo[1])))
    grow = margin * max(float(np.median(sides)), 1e-9)
    held = set(test)
    owner_of = np.full(len(names), -1)
    for k, cell in enumerate(cells):
        owner_of[cell.contains_plane(foot)] = k
    blocks, seam_views = [], []
    for k, cell in enumerate(cells):
        grown = cell.grown(grow)
        inside = grown.contains_plane(uv)
        train = [names[i] for i, s in enumerate(seen) if names[i] not in held
                 and ((len(s) and inside[s].mean() >= min_share) or owner_of[i] == k)]
        tests = [names[i] for i in range(len(names)) if names[i] in held and owner_of[i] == k]
        name = f"block{k + 1:02d}"
        if len(train) < MIN_BLOCK_VIEWS:
            raise RecGSError(f"{scene.scene_dir}: {name} of {n} would train on {len(train)} photo(s) (at least "
                             f"{MIN_BLOCK_VIEWS}); split the survey into fewer blocks")
        blocks.append(Block(name, cell, grown, train, tests, int(grown.contains(scene.points).sum())))
    for i, name in enumerate(names):
        if name in held and len(seen[i]):
            share = cells[owner_of[i]].contains_plane(uv[seen[i]]).mean()
            if share < SEAM_SHARE:
                seam_views.append(name)
    owner = {names[i]: blocks[owner_of[i]].name for i in range(len(names))}
    return BlockPlan(blocks, (cols, rows), grow, sorted(held & set(names)), sorted(seam_views), owner)


def fewest_duplicating(scene: Scene, test: list[str], n: int, max_duplication: float = MAX_DUPLICATION) -> int:
    """The most blocks, up to ``n``, whose split trains each photo in at most ``max_duplication``
    blocks on average (1: none does, one job)."""
    geometry = split_geometry(scene) if n > 1 else None
    for k in range(n, 1, -1):
        try:
            if plan_blocks(scene, k, test, geometry=geometry).duplication <= max_duplication:
                return k
        except RecGSError:
            continue
    return 1


def check_split(scene: Scene, plan: BlockPlan, test: list[str], cluster: bool) -> None:
    """Refuse (RecGSError) a split on one machine that trains each photo in more than
    :data:`MAX_DUPLICATION` blocks on average, with the count that would not; on a cluster the
    blocks bring more machines, and the plan only says what they cost."""
    if cluster or plan.duplication <= MAX_DUPLICATION:
        return
    n = len(plan.blocks)
    fits = fewest_duplicating(scene, test, n - 1)
    advice = "train it as one job (--blocks 0)" if fits <= 1 else f"split it into at most {fits} blocks"
    raise RecGSError(f"{scene.scene_dir}: {n} blocks would train each photo in {plan.duplication:.1f} of them on "
                     f"average (the survey is a few photos' footprints wide): on this machine's cores each photo "
                     f"would get {1 / plan.duplication:.2f} of one job's steps; {advice}, or --blocks auto")


def auto_blocks(scene: Scene, test: list[str], one_job_bytes: int, available: Optional[int],
                most: int = 64) -> tuple[int, str]:
    """``--blocks auto``: how many blocks, and why. One job where its planned memory
    (``one_job_bytes``) fits in ``available`` (on one machine the blocks share its cores, so they
    only duplicate photos); otherwise the fewest blocks whose share of the survey (its photos
    times their duplication) fits."""
    if available is None or one_job_bytes <= available:
        gb = lambda b: f"{b / 2 ** 30:.1f} GB"  # noqa: E731
        room = "" if available is None else f" of {gb(available)}"
        return 1, f"one job: it needs about {gb(one_job_bytes)}{room}, and blocks would only duplicate photos"
    geometry = split_geometry(scene)
    for k in range(2, most + 1):
        try:
            plan = plan_blocks(scene, k, test, geometry=geometry)
        except RecGSError:
            break
        if one_job_bytes * plan.duplication / k <= available:
            return k, (f"{k} blocks: one job would need about {one_job_bytes / 2 ** 30:.1f} GB of "
                       f"{available / 2 ** 30:.1f} GB; {plan.cost_line()}")
    raise RecGSError(f"{scene.scene_dir}: no split into up to {most} blocks fits in memory "
                     f"({one_job_bytes / 2 ** 30:.1f} GB for one job, {available / 2 ** 30:.1f} GB available); "
                     "train at a lower resolution (--max-side)")
