"""Analytic terrain with obstacles and true risk, in local UTM coordinates.

Local coordinates (u, v) [m] are (E - origin_e, N - origin_n) of the drive's projected
CRS; heights are NAVD88-like orthometric metres. The smooth part is a closed-form
function; rocks and trees are radial bumps. Evaluation on regular grids is exact;
arbitrary points are sampled bilinearly from exact 0.1 m tiles (error well under 1 cm),
which keeps the simulator fast.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from gtgen.config import SynthConfig

TILE_CELLS = 512
TILE_SHIFT = 9  # TILE_CELLS == 1 << TILE_SHIFT
TILE_RES_M = 0.1
BASE_HEIGHT_M = 240.0


@dataclass(frozen=True)
class Obstacles:
    """Rocks, trees and bushes: centres (u, v) [m], radii and heights [m], and their risk."""

    rock_uv: NDArray[np.float64]
    rock_radius: NDArray[np.float64]
    rock_height: NDArray[np.float64]
    tree_uv: NDArray[np.float64]
    trunk_radius: NDArray[np.float64]
    canopy_radius: NDArray[np.float64]
    tree_height: NDArray[np.float64]
    bush_uv: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    bush_radius: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    bush_height: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class Changes:
    """Patches where the terrain changed since the DEM survey: centres (u, v), radii and
    height changes [m] (+ berm, - cut). The world has them, the DEM does not."""

    uv: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    radius: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    dh: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    def height(self, u: NDArray, v: NDArray) -> NDArray[np.float64]:
        """Return the change at (u, v): a smooth dome or bowl per patch."""
        out = np.zeros(np.broadcast(u, v).shape)
        for (cu, cv), r, dh in zip(self.uv, self.radius, self.dh):
            q = np.clip(1 - ((u - cu) ** 2 + (v - cv) ** 2) / r**2, 0, None)
            out += dh * q**2
        return out


def place_changes(cfg: SynthConfig, path_uv: NDArray) -> Changes:
    """Return ``terrain_changes`` seeded patches on the path (berms and cuts alternating)."""
    if not cfg.terrain_changes:
        return Changes()
    rng = np.random.default_rng([cfg.seed, 8])
    idx = np.sort(rng.integers(len(path_uv) // 10, len(path_uv) - len(path_uv) // 10, cfg.terrain_changes))
    sign = np.where(np.arange(cfg.terrain_changes) % 2 == 0, 1.0, -1.0)
    return Changes(path_uv[idx] + rng.normal(0, 3.0, (len(idx), 2)), np.full(len(idx), cfg.terrain_change_radius_m),
                   sign * cfg.terrain_change_m)


def place_obstacles(cfg: SynthConfig, bounds: tuple[float, float, float, float], path_uv: NDArray) -> Obstacles:
    """Return seeded rocks and trees inside ``bounds`` (u0, v0, u1, v1), clear of the path."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng([cfg.seed, 2])
    u0, v0, u1, v1 = bounds
    area_ha = (u1 - u0) * (v1 - v0) / 1e4
    path = cKDTree(path_uv[:: max(1, len(path_uv) // 4000)])

    def draw(density: float, clearance: float) -> NDArray:
        n = rng.poisson(density * area_ha)
        uv = np.column_stack([rng.uniform(u0, u1, n), rng.uniform(v0, v1, n)])
        d, _ = path.query(uv)
        return uv[d > clearance]

    rock_uv = draw(cfg.rocks_per_ha, 2.5)
    tree_uv = draw(cfg.trees_per_ha, 6.0)
    nr, nt = len(rock_uv), len(tree_uv)
    # Planted trees close beside the path make sure every drive sees some up close;
    # they are full-grown so that they are unmistakable in every sensor.
    idx = rng.integers(0, len(path_uv), size=max(3, int(len(path_uv) * 1e-3)))
    side = rng.choice([-1.0, 1.0], size=len(idx))
    tangent = np.gradient(path_uv, axis=0)[idx]
    normal = np.column_stack([-tangent[:, 1], tangent[:, 0]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-12
    near = path_uv[idx] + normal * (side * rng.uniform(9.0, 16.0, len(idx)))[:, None]
    d, _ = path.query(near)
    near = near[d > 6.0]
    npl = len(near)
    bush_uv = _bushes(cfg, bounds, path)
    nb = len(bush_uv)
    brng = np.random.default_rng([cfg.seed, 7])
    return Obstacles(
        bush_uv=bush_uv, bush_radius=brng.uniform(1.0, 2.5, nb), bush_height=brng.uniform(cfg.bush_height_min_m, cfg.bush_height_max_m, nb),
        rock_uv=rock_uv,
        rock_radius=rng.uniform(0.3, 0.9, nr),
        rock_height=rng.uniform(0.3, 0.8, nr),
        tree_uv=np.vstack([tree_uv, near]),
        trunk_radius=np.concatenate([rng.uniform(0.15, 0.35, nt), rng.uniform(0.3, 0.4, npl)]),
        canopy_radius=np.concatenate([rng.uniform(1.5, 3.5, nt), rng.uniform(2.5, 3.5, npl)]),
        tree_height=np.concatenate([rng.uniform(cfg.tree_height_min_m, cfg.tree_height_max_m, nt), rng.uniform(7.0, 10.0, npl)]),
    )


def _bushes(cfg: SynthConfig, bounds: tuple[float, float, float, float], path) -> NDArray:
    """Seeded bush centres, clear of the path (their own random stream: none by default)."""
    if not cfg.bushes_per_ha:
        return np.zeros((0, 2))
    rng = np.random.default_rng([cfg.seed, 9])
    u0, v0, u1, v1 = bounds
    n = rng.poisson(cfg.bushes_per_ha * (u1 - u0) * (v1 - v0) / 1e4)
    uv = np.column_stack([rng.uniform(u0, u1, n), rng.uniform(v0, v1, n)])
    return uv[path.query(uv)[0] > 3.0]


def _window(cu: float, cv: float, rad: float, u0: float, v0: float, res: float, nu: int, nv: int) -> tuple[slice, slice] | None:
    """Return the cells of an (nu, nv) grid at origin (u0, v0) within ``rad`` of (cu, cv)
    along each axis, or None when none is."""
    i0 = max(int(np.floor((cu - rad - u0) / res)), 0)
    i1 = min(int(np.ceil((cu + rad - u0) / res)) + 1, nu)
    j0 = max(int(np.floor((cv - rad - v0) / res)), 0)
    j1 = min(int(np.ceil((cv + rad - v0) / res)) + 1, nv)
    if i0 >= i1 or j0 >= j1:
        return None
    return slice(i0, i1), slice(j0, j1)


class Terrain:
    """The true world of a synthetic drive: ground, obstacle surface and risk."""

    def __init__(self, cfg: SynthConfig, obstacles: Obstacles, changes: Changes | None = None) -> None:
        rng = np.random.default_rng([cfg.seed, 1])
        self.cfg = cfg
        self.obstacles = obstacles
        self.changes = changes or Changes()
        k = 6
        self._wave_amp = cfg.hill_amplitude_m * rng.uniform(0.3, 1.0, k) / np.sqrt(k / 2)
        lam = rng.uniform(90.0, 450.0, k)
        ang = rng.uniform(0, np.pi, k)
        self._wave_k = np.column_stack([np.cos(ang), np.sin(ang)]) * (2 * np.pi / lam)[:, None]
        self._wave_phase = rng.uniform(0, 2 * np.pi, k)
        if cfg.crest_amplitude_m > 0:  # short hills and crests, their own stream (the easy world has none)
            crng = np.random.default_rng([cfg.seed, 16])
            kc = 8
            amp = cfg.crest_amplitude_m * crng.uniform(0.4, 1.0, kc) / np.sqrt(kc / 2)
            ang_c = crng.uniform(0, np.pi, kc)
            lam_c = crng.uniform(30.0, 80.0, kc)
            self._wave_amp = np.concatenate([self._wave_amp, amp])
            self._wave_k = np.vstack([self._wave_k, np.column_stack([np.cos(ang_c), np.sin(ang_c)]) * (2 * np.pi / lam_c)[:, None]])
            self._wave_phase = np.concatenate([self._wave_phase, crng.uniform(0, 2 * np.pi, kc)])
        va = rng.uniform(0, np.pi)
        self._valley_dir = np.array([np.cos(va), np.sin(va)])
        self._valley_pt = rng.uniform(-80, 80, 2)
        nd = 5
        da = rng.uniform(0, np.pi, nd)
        self._ditch_dir = np.column_stack([np.cos(da), np.sin(da)])
        self._ditch_pt = rng.uniform(-150, 150, (nd, 2))
        self._ditch_depth = cfg.ditch_depth_m * rng.uniform(0.6, 1.0, nd)
        self._ditch_width = rng.uniform(0.4, 0.8, nd)
        self._tiles: OrderedDict[tuple[int, int], int] = OrderedDict()  # tile key -> pool slot
        self._pool: NDArray[np.float32] | None = None  # (max_tiles, n, n, layers), made on first use
        self._pool_file: str | None = None  # where the pool lies for other processes (``share``)
        self.max_tiles = 112

    def share(self, folder: Path) -> None:
        """Put the evaluated tiles in a file of ``folder``, so that a pickle of this terrain
        names the file and each process that unpickles it maps the tiles (copy on write)
        instead of receiving them or evaluating them again."""
        if self._pool is None:
            return
        folder.mkdir(parents=True, exist_ok=True)
        self._pool_file = str(folder / "terrain_tiles.npy")
        np.save(self._pool_file, self._pool)

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        if self._pool_file is not None:
            state["_pool"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if self._pool_file is not None and self._pool is None:
            self._pool = np.load(self._pool_file, mmap_mode="c")

    # -- exact evaluation on regular grids -------------------------------------------
    def smooth(self, u: NDArray, v: NDArray) -> NDArray[np.float64]:
        """Return the obstacle-free ground height [m] at (u, v)."""
        h = np.full(np.broadcast(u, v).shape, BASE_HEIGHT_M)
        for a, kk, ph in zip(self._wave_amp, self._wave_k, self._wave_phase):
            h += a * np.sin(kk[0] * u + kk[1] * v + ph)
        n = np.array([-self._valley_dir[1], self._valley_dir[0]])
        d = (u - self._valley_pt[0]) * n[0] + (v - self._valley_pt[1]) * n[1]
        h -= self.cfg.valley_depth_m * np.exp(-0.5 * (d / 45.0) ** 2)
        for dd, pt, depth, w in zip(self._ditch_dir, self._ditch_pt, self._ditch_depth, self._ditch_width):
            dn = (u - pt[0]) * -dd[1] + (v - pt[1]) * dd[0]
            h -= depth * np.exp(-0.5 * (dn / w) ** 2)
        return h

    def smooth_grid(self, u: NDArray, v: NDArray) -> NDArray[np.float64]:
        """Return ``smooth`` on the grid of ``u`` (nu,) x ``v`` (nv,), (nu, nv): each wave
        sin(a_i + b_j) as sin a_i cos b_j + cos a_i sin b_j, all waves in one matrix product
        (trigonometry per row and column, not per cell), and each ditch only on the cells
        within 8.5 widths of its line (beyond, its Gaussian is below 1e-15 of its depth).
        Equal to ``smooth`` (the oracle) within 1e-9 m."""
        a = np.outer(u, self._wave_k[:, 0])  # (nu, waves)
        b = np.outer(v, self._wave_k[:, 1]) + self._wave_phase  # (nv, waves)
        amp = self._wave_amp
        h = np.hstack([np.sin(a) * amp, np.cos(a) * amp]) @ np.vstack([np.cos(b).T, np.sin(b).T]) + BASE_HEIGHT_M
        n = np.array([-self._valley_dir[1], self._valley_dir[0]])
        d = ((u - self._valley_pt[0]) * n[0])[:, None] + ((v - self._valley_pt[1]) * n[1])[None, :]
        h -= self.cfg.valley_depth_m * np.exp(-0.5 * (d / 45.0) ** 2)
        for dd, pt, depth, w in zip(self._ditch_dir, self._ditch_pt, self._ditch_depth, self._ditch_width):
            dn = ((u - pt[0]) * -dd[1])[:, None] + ((v - pt[1]) * dd[0])[None, :]
            near = np.abs(dn) < 8.5 * w
            h[near] -= depth * np.exp(-0.5 * (dn[near] / w) ** 2)
        return h

    def eval_grid(self, u0: float, v0: float, res: float, nu: int, nv: int, surveyed: bool = False) -> dict[str, NDArray[np.float32]]:
        """Return exact layers on the grid of cell centres u0 + (i + .5) res, v0 + (j + .5) res.

        Layers: ``ground`` (bare earth + rocks) [m], ``bare`` (bare earth) [m],
        ``surface`` (ground + tree crowns and bushes, what occludes) [m], ``risk`` [0..1].
        ``surveyed``: the terrain as the DEM survey saw it, before the terrain changes.
        """
        u = u0 + (np.arange(nu) + 0.5) * res
        v = v0 + (np.arange(nv) + 0.5) * res
        U, V = np.meshgrid(u, v, indexing="ij")
        bare = self.smooth_grid(u, v)
        if len(self.changes.dh) and not surveyed:
            bare += self.changes.height(U, V)
        ground = bare.copy()
        surface_extra = np.zeros_like(bare)
        risk = np.zeros_like(bare)
        ob = self.obstacles

        def window(cu: float, cv: float, rad: float) -> tuple[slice, slice] | None:
            return _window(cu, cv, rad, u0, v0, res, nu, nv)

        for (cu, cv), r, hgt in zip(ob.rock_uv, ob.rock_radius, ob.rock_height):
            w = window(cu, cv, 2.5 * r)
            if w is None:
                continue
            d2 = (U[w] - cu) ** 2 + (V[w] - cv) ** 2
            bump = hgt * np.exp(-0.5 * d2 / (0.5 * r) ** 2)
            ground[w] += bump
            risk[w] = np.maximum(risk[w], np.clip(bump / 0.35, 0, 1) * 0.8)
        for (cu, cv), tr, cr, th in zip(ob.tree_uv, ob.trunk_radius, ob.canopy_radius, ob.tree_height):
            w = window(cu, cv, cr + 1.0)
            if w is None:
                continue
            d = np.sqrt((U[w] - cu) ** 2 + (V[w] - cv) ** 2)
            crown = np.where(d < cr, th * np.sqrt(np.clip(1 - (d / cr) ** 2, 0, 1)) * 0.3 + th * 0.7, 0.0)
            crown = np.where(d < tr, th, crown)
            surface_extra[w] = np.maximum(surface_extra[w], crown)
            tree_risk = np.where(d < tr + 0.5, 1.0, np.where(d < cr, 0.6, 0.0))
            risk[w] = np.maximum(risk[w], tree_risk)
        for (cu, cv), br, bh in zip(ob.bush_uv, ob.bush_radius, ob.bush_height):
            w = window(cu, cv, br)
            if w is None:
                continue
            q = np.clip(1 - ((U[w] - cu) ** 2 + (V[w] - cv) ** 2) / br**2, 0, None)
            surface_extra[w] = np.maximum(surface_extra[w], bh * np.sqrt(q))
            risk[w] = np.maximum(risk[w], np.where(q > 0, 0.3, 0.0))
        gy, gx = np.gradient(ground, res)
        slope = np.hypot(gx, gy)
        risk = np.maximum(risk, np.clip((slope - 0.25) / 0.6, 0, 1) * 0.5)
        return {
            "ground": ground.astype(np.float32),
            "bare": bare.astype(np.float32),
            "surface": (ground + surface_extra).astype(np.float32),
            "risk": risk.astype(np.float32),
        }

    # -- fast sampling at arbitrary points ---------------------------------------------
    _LAYERS = ("ground", "bare", "surface", "risk")

    def _tile(self, key: tuple[int, int]) -> NDArray[np.float32]:
        """Return the (n, n, 4) layers of tile ``key`` (evaluated once, kept in an LRU pool)."""
        slot = self._slot(key)  # allocates the pool on first use
        assert self._pool is not None
        return self._pool[slot]

    def _slot(self, key: tuple[int, int]) -> int:
        slot = self._tiles.get(key)
        if slot is not None:
            self._tiles.move_to_end(key)
            return slot
        n = TILE_CELLS + 1
        if self._pool is None:
            # layers last: the four layers of a cell and of its +v neighbour share a cache line
            self._pool = np.empty((self.max_tiles, n, n, len(self._LAYERS)), np.float32)
        if len(self._tiles) >= self.max_tiles:
            _, slot = self._tiles.popitem(last=False)
        else:
            slot = len(self._tiles)
        edge = TILE_CELLS * TILE_RES_M
        # one cell of overlap so bilinear lookups never cross a tile border
        g = self.eval_grid(key[0] * edge - 0.5 * TILE_RES_M, key[1] * edge - 0.5 * TILE_RES_M, TILE_RES_M, n, n)
        for i, name in enumerate(self._LAYERS):
            self._pool[slot, :, :, i] = g[name]
        self._tiles[key] = slot
        return slot

    def sample(self, u: NDArray, v: NDArray, layers: tuple[str, ...] = ("ground",)) -> list[NDArray[np.float32]]:
        """Return the named layers bilinearly sampled at points (u, v) of any shape.

        The tiles under the points' bounding box are looked up once; each point then
        gathers its four neighbours from the tile pool by flat index (no sorting).
        """
        shape, iu, iv, au, av = _cells(u, v)
        if iu.size == 0:
            return [np.zeros(shape, np.float32) for _ in layers]
        tu, tv = iu >> TILE_SHIFT, iv >> TILE_SHIFT  # floor division by TILE_CELLS
        tu0, tv0 = int(tu.min()), int(tv.min())
        nt_u, nt_v = int(tu.max()) - tu0 + 1, int(tv.max()) - tv0 + 1
        if nt_u * nt_v > self.max_tiles // 2:
            return self.sample_grouped(u, v, layers)
        n = TILE_CELLS + 1
        # touch every tile first, so that none needed here is evicted while filling others
        lut = np.array([[self._slot((tu0 + a, tv0 + b)) for b in range(nt_v)] for a in range(nt_u)], np.int64)
        L = len(self._LAYERS)
        flat = lut[tu - tu0, tv - tv0] * (n * n) + (iu & (TILE_CELLS - 1)) * n + (iv & (TILE_CELLS - 1))
        # items of two neighbouring cells (along v) with all their layers: one gather each
        item = np.dtype((np.void, 2 * L * 4))
        pairs = np.ndarray((self._pool.size // L - 1,), dtype=item, buffer=self._pool, strides=(L * 4,))
        # (N, 2, L): cells (i, j), (i, j+1) and (i+1, j), (i+1, j+1)
        lo = pairs[flat].view(np.float32).reshape(-1, 2, L)
        hi = pairs[flat + n].view(np.float32).reshape(-1, 2, L)
        w00 = (1 - au) * (1 - av)
        w10 = au * (1 - av)
        w01 = (1 - au) * av
        w11 = au * av
        out = []
        for name in layers:
            li = self._LAYERS.index(name)
            out.append((lo[:, 0, li] * w00 + hi[:, 0, li] * w10 + lo[:, 1, li] * w01 + hi[:, 1, li] * w11).reshape(shape))
        return out

    def sample_grouped(self, u: NDArray, v: NDArray, layers: tuple[str, ...] = ("ground",)) -> list[NDArray[np.float32]]:
        """``sample`` tile by tile (points grouped by a sort): for huge extents, and the test oracle."""
        shape, iu, iv, au, av = _cells(u, v)
        tu, tv = iu // TILE_CELLS, iv // TILE_CELLS
        lu, lv = iu - tu * TILE_CELLS, iv - tv * TILE_CELLS
        li = [self._LAYERS.index(name) for name in layers]
        out = np.empty((len(li), iu.size), np.float32)
        keys = tu * 1_000_003 + tv
        order = np.argsort(keys, kind="stable")
        uniq, starts = np.unique(keys[order], return_index=True)
        bounds = np.append(starts, len(order))
        n = TILE_CELLS + 1
        for k in range(len(uniq)):
            sel = order[bounds[k] : bounds[k + 1]]
            tile = self._tile((int(tu[sel[0]]), int(tv[sel[0]])))
            flat = lu[sel] * n + lv[sel]
            wa, wb = au[sel], av[sel]
            w00 = (1 - wa) * (1 - wb)
            w10 = wa * (1 - wb)
            w01 = (1 - wa) * wb
            w11 = wa * wb
            for row, layer in enumerate(li):
                t = tile[..., layer].ravel()
                out[row, sel] = t[flat] * w00 + t[flat + n] * w10 + t[flat + 1] * w01 + t[flat + n + 1] * w11
        return [o.reshape(shape) for o in out]


def _cells(u: NDArray, v: NDArray) -> tuple[tuple[int, ...], NDArray, NDArray, NDArray, NDArray]:
    """Return (shape, iu, iv, au, av): the 0.1 m cell of each point (flattened) and its
    bilinear weights along u and v (``gtgen.grids.cell_weights``, the one rule)."""
    from gtgen.grids import cell_weights

    u = np.asarray(u, dtype=np.float64)
    iu, au = cell_weights(u.ravel() / TILE_RES_M)
    iv, av = cell_weights(np.asarray(v, dtype=np.float64).ravel() / TILE_RES_M)
    return u.shape, iu, iv, au, av
