"""Hindsight fusion of one range's maps into each sample's target grid.

Semantics (data_schema.md, 'Regions'), for a sample at t with current map m0 (the latest
map stamped <= t) and window [a, b] = [min(t - past, t_m0), t + window]:

- elevation: mean over maps in the window where the cell is finite and
  confidence > min_conf, minus the base z at t (rule ``mean``, the paper's); with rule
  ``ground`` the mean over those maps where the cell is not in the map's top layer
  (``lattice.top_layer``: crowns, bushes), falling back to the mean of all where every
  observation was top layer (a rock or a crown seen only from above: all agree);
- confidence: max over maps in the window;
- risk: the value of the latest map in the window with confidence >= risk_min_conf;
- count, last observation: how many maps gave the elevation, and the latest confident
  one's stamp;
- region: 1 where m0 is confident (> min_conf), else 2 where some map in the window
  is, else 3 (unobserved; the DEM stage fills or zeroes these).

The confidence, the last observation's stamp and X-Racer's confidence at t are QA grids
(``schema.QA_GRIDS``: no label, region or training input depends on them): with
``FuseParams.qa`` false they are not computed (None), and the window maxima below are
not run at all, about a quarter of fuse's time.

Cost: ``fuse_range`` splats every map into odom-lattice accumulators a fixed number of
times whatever the window: sums and counts slide (add at b, subtract past a), the
latest risk and last-observation stamps are overwritten in time order and expire past
a, and the max confidence uses the van Herk / Gil-Werman split of the window into a
suffix of one block and a prefix of the next (blocks of the window's length). Each
sample then gathers a handful of lattice fields. ``naive_fuse_range`` is the oracle.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gtgen import codes
from gtgen.fuse.lattice import Atlas, LatticeMap, gather_map, target_lattice_index, top_layer

ELEVATION_RULES = ("mean", "ground")


@dataclass(frozen=True)
class FuseParams:
    """Fusion settings in gtgen units (ns, confidence)."""

    window_ns: int
    past_ns: int = 0
    min_conf: float = 0.1
    risk_min_conf: float = 0.5
    tile: int = 128
    elevation_rule: str = "mean"
    top_height_m: float = 0.5
    top_footprint_m: float = 8.0
    qa: bool = True  # compute the QA grids (confidence, last observation, X-Racer's confidence)

    def __post_init__(self) -> None:
        if self.elevation_rule not in ELEVATION_RULES:
            raise ValueError(f"elevation rule {self.elevation_rule!r}; expected one of {list(ELEVATION_RULES)}")

    @property
    def ground(self) -> bool:
        """Whether observations in a map's top layer are kept apart (rule ``ground``)."""
        return self.elevation_rule == "ground"


def ground_obs(m: LatticeMap, p: FuseParams) -> NDArray[np.bool_] | None:
    """Return the cells of map ``m`` that observe the ground under rule ``ground`` (computed
    once per loaded map), None under rule ``mean``."""
    if not p.ground:
        return None
    if m.top is None:
        m.top = top_layer(m, p.min_conf, p.top_footprint_m, p.top_height_m)
    return ~m.top


@dataclass(frozen=True)
class SampleGrid:
    """A sample's target grid: time, base position (odom) and yaw, grid size and resolution."""

    t_ns: int
    pos: NDArray[np.float64]
    yaw: float
    current_map: int
    size: int
    res: float


@dataclass
class Fused:
    """One sample's fused labels and its X-Racer map at t, all (size, size); the QA grids
    (confidence, last_dt_s, xr_confidence) None when not computed (``FuseParams.qa``)."""

    elevation: NDArray[np.float32]
    confidence: NDArray[np.float32] | None
    risk: NDArray[np.float32]
    count: NDArray[np.uint16]
    last_dt_s: NDArray[np.float32] | None
    region: NDArray[np.uint8]
    xr_elevation: NDArray[np.float32]
    xr_risk: NDArray[np.float32]
    xr_confidence: NDArray[np.float32] | None


class MapSource:
    """Maps of one range by index, sorted by stamp, loaded lazily with a small cache."""

    def __init__(self, t_ns: NDArray[np.int64], load: Callable[[int], LatticeMap], cache: int = 6) -> None:
        if len(t_ns) > 1 and np.any(np.diff(t_ns) < 0):
            raise ValueError("map stamps must be sorted")
        self.t_ns = np.asarray(t_ns, dtype=np.int64)
        self._load = load
        self._cache: OrderedDict[int, LatticeMap] = OrderedDict()
        self._size = cache
        self.loads = 0

    def __len__(self) -> int:
        return len(self.t_ns)

    def __getitem__(self, i: int) -> LatticeMap:
        m = self._cache.get(i)
        if m is None:
            m = self._load(i)
            self.loads += 1
            self._cache[i] = m
            if len(self._cache) > self._size:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(i)
        return m

    @classmethod
    def from_list(cls, maps: list[LatticeMap]) -> MapSource:
        maps = sorted(maps, key=lambda m: m.t_ns)
        return cls(np.array([m.t_ns for m in maps], np.int64), lambda i: maps[i], cache=1)


def window_bounds(s: SampleGrid, maps: MapSource, p: FuseParams) -> tuple[int, int]:
    """Return the window [a, b] [ns] of sample ``s``."""
    a = s.t_ns - p.past_ns
    if 0 <= s.current_map < len(maps):
        a = min(a, int(maps.t_ns[s.current_map]))
    return a, s.t_ns + p.window_ns


def _finish(s: SampleGrid, I: NDArray, J: NDArray, maps: MapSource, p: FuseParams,
            ssum: NDArray, cnt: NDArray, risk: NDArray, last: NDArray | None, cmax: NDArray | None,
            gsum: NDArray | None = None, gcnt: NDArray | None = None) -> Fused:
    z = s.pos[2]
    used = cnt
    if gsum is not None and gcnt is not None:  # rule ground: the ground observations where there are any
        ssum, used = np.where(gcnt > 0, gsum, ssum), np.where(gcnt > 0, gcnt, cnt)
    with np.errstate(invalid="ignore", divide="ignore"):
        elev = np.where(used > 0, ssum / np.maximum(used, 1) - z, np.nan).astype(np.float32)
    if 0 <= s.current_map < len(maps):
        xe, xr, xc = gather_map(maps[s.current_map], I, J)
    else:
        xe = xr = xc = np.full(I.shape, np.nan)
    cur = np.isfinite(xe) & (xc > p.min_conf)
    region = np.where(cur, codes.OBS_PC, np.where(cnt > 0, codes.OBS_F, codes.UNOBS)).astype(np.uint8)
    conf = last_dt = xr_conf = None
    if p.qa:
        conf = np.where(np.isfinite(cmax), cmax, np.nan).astype(np.float32)
        last_dt = np.where(last >= 0, (last - s.t_ns) * 1e-9, np.nan).astype(np.float32)
        xr_conf = xc.astype(np.float32)
    return Fused(
        elevation=elev, confidence=conf, risk=risk.astype(np.float32), count=np.minimum(used, 65535).astype(np.uint16),
        last_dt_s=last_dt, region=region,
        xr_elevation=(xe - z).astype(np.float32), xr_risk=xr.astype(np.float32), xr_confidence=xr_conf,
    )


def naive_fuse_range(maps: MapSource, samples: list[SampleGrid], p: FuseParams) -> Iterator[tuple[int, Fused]]:
    """Yield (index, Fused) per sample by re-fusing every map of its window: the oracle."""
    for k, s in enumerate(samples):
        a, b = window_bounds(s, maps, p)
        I, J = target_lattice_index(s.size, s.res, s.res, s.pos, s.yaw)
        ssum = np.zeros(I.shape)
        cnt = np.zeros(I.shape, np.int64)
        cmax = np.full(I.shape, -np.inf)
        risk = np.full(I.shape, np.nan)
        last = np.full(I.shape, -1, np.int64)
        gsum, gcnt = (np.zeros(I.shape), np.zeros(I.shape, np.int64)) if p.ground else (None, None)
        for i in np.nonzero((maps.t_ns >= a) & (maps.t_ns <= b))[0]:  # stamp order
            m = maps[int(i)]
            e, r, c = gather_map(m, I, J)
            obs = np.isfinite(e) & (c > p.min_conf)
            ssum += np.where(obs, e, 0.0)
            cnt += obs
            g = ground_obs(m, p)
            if g is not None:
                gobs = obs & (gather_map(m, I, J, layer=g)[0] == 1)
                gsum += np.where(gobs, e, 0.0)
                gcnt += gobs
            cmax = np.fmax(cmax, np.where(np.isfinite(c), c, -np.inf))
            robs = np.isfinite(r) & (c >= p.risk_min_conf)
            risk = np.where(robs, r, risk)
            last = np.where(obs, maps.t_ns[i], last)
        yield k, _finish(s, I, J, maps, p, ssum, cnt, risk, last, cmax, gsum, gcnt)


# elevation sums in integer micrometres: exact under any order of adds and subtracts, so
# a drive fused in time chunks gives bit-identical labels to one pass
SUM_SCALE = 1e6
_SLIDE = {"sum": ("int64", 0), "cnt": ("int32", 0), "risk": ("float32", np.nan), "rstamp": ("int64", -1)}
_LAST = {"lstamp": ("int64", -1)}  # the last observation's stamp: a QA grid's
_GROUND = {"gsum": ("int64", 0), "gcnt": ("int32", 0)}  # rule ground: sums of the ground observations
_MAX = {"max": ("float32", -np.inf)}


class _Sliding:
    """Sums and counts over a sliding window; latest risk / observation by overwrite + expiry.

    Windows only move forward. A map is added when the window's end passes it (unless
    it is already behind the window's start) and subtracted when the start passes it.
    """

    def __init__(self, maps: MapSource, p: FuseParams) -> None:
        self.maps, self.p = maps, p
        self.atlas = Atlas(p.tile, {**_SLIDE, **(_LAST if p.qa else {}), **(_GROUND if p.ground else {})})
        self.next_add = 0
        self.added: list[int] = []  # added and not yet subtracted, in stamp order

    def _splat(self, i: int, sign: int) -> None:
        """Add (``sign`` +1) or subtract (-1) map ``i`` into the lattice tiles it covers.

        Its observations and their integer sums are made once over the whole map, then
        added to or taken from each tile in place (the same integers as per tile)."""
        m = self.maps[i]
        t = int(m.t_ns)
        d = self.atlas.data
        c = m.confidence
        obs = np.isfinite(m.elevation)
        obs &= c > self.p.min_conf
        v = m.elevation * SUM_SCALE
        np.rint(v, out=v)  # np.round's rounding (half to even)
        v[~obs] = 0
        ie = v.astype(np.int64)
        ground = ground_obs(m, self.p)
        if ground is not None:
            gie, gobs = np.where(ground, ie, 0), obs & ground
        if sign > 0:
            robs = np.isfinite(m.risk)
            robs &= c >= self.p.risk_min_conf
        add = np.add if sign > 0 else np.subtract
        for slot, dst, src in self.atlas.windows(m.i0, m.j0, *m.shape, t, create=sign > 0):
            for name, x in (("sum", ie), ("cnt", obs)) + ((("gsum", gie), ("gcnt", gobs)) if ground is not None else ()):
                tile = d[name][slot][dst]
                add(tile, x[src], out=tile)
            if sign > 0:
                np.copyto(d["risk"][slot][dst], m.risk[src], where=robs[src])
                np.copyto(d["rstamp"][slot][dst], t, where=robs[src])
                if self.p.qa:
                    np.copyto(d["lstamp"][slot][dst], t, where=obs[src])

    def advance(self, a: int, b: int) -> None:
        """Move the window to [a, b] (both never decrease)."""
        t = self.maps.t_ns
        while self.next_add < len(t) and t[self.next_add] <= b:
            if t[self.next_add] >= a:
                self._splat(self.next_add, +1)
                self.added.append(self.next_add)
            self.next_add += 1
        while self.added and t[self.added[0]] < a:
            self._splat(self.added.pop(0), -1)
        self.atlas.release_older_than(a)

    def gather(self, I: NDArray, J: NDArray, a: int) -> tuple[NDArray, ...]:
        """Return (sum, count, risk, last stamp, ground sum, ground count) at lattice cells
        (I, J) for a window starting at ``a`` (the last stamp None without the QA grids, the
        ground ones None under rule ``mean``)."""
        names = ("sum", "cnt", "risk", "rstamp") + (("lstamp",) if self.p.qa else ()) + (("gsum", "gcnt") if self.p.ground else ())
        got = dict(zip(names, self.atlas.gather(I, J, names)))  # one lookup of the cells' tiles
        ssum = got["sum"] / SUM_SCALE
        risk = np.where(got["rstamp"] >= a, got["risk"], np.nan)
        lstamp = np.where(got["lstamp"] >= a, got["lstamp"], -1) if self.p.qa else None
        gsum = gcnt = None
        if self.p.ground:
            gsum, gcnt = got["gsum"] / SUM_SCALE, got["gcnt"]
        return ssum, got["cnt"], risk, lstamp, gsum, gcnt


def _max_splat(atlas: Atlas, m: LatticeMap) -> None:
    for slot, dst, src in atlas.windows(m.i0, m.j0, *m.shape, int(m.t_ns)):
        d = atlas.data["max"]  # looked up per tile: allocating a tile may grow the array
        c = m.confidence[src]
        d[slot][dst] = np.fmax(d[slot][dst], np.where(np.isfinite(c), c, -np.inf))


def fuse_range(maps: MapSource, samples: list[SampleGrid], p: FuseParams) -> Iterator[tuple[int, Fused]]:
    """Yield (index, Fused) per sample, in time order, equal to ``naive_fuse_range``."""
    if not samples:
        return
    order = sorted(range(len(samples)), key=lambda k: samples[k].t_ns)
    bounds = {k: window_bounds(samples[k], maps, p) for k in order}
    if any(bounds[order[i]][0] > bounds[order[i + 1]][0] for i in range(len(order) - 1)):
        raise ValueError("window starts must not decrease with sample time: each sample's current map must be the latest map stamped <= t")
    sliding = _Sliding(maps, p)
    cells = _window_maxima(maps, samples, order, bounds, p.tile) if p.qa else ((k, *_cells(samples[k]), None) for k in order)
    for k, I, J, cmax in cells:
        a, b = bounds[k]
        sliding.advance(a, b)
        ssum, cnt, risk, last, gsum, gcnt = sliding.gather(I, J, a)
        yield k, _finish(samples[k], I, J, maps, p, ssum, cnt, risk, last, cmax, gsum, gcnt)


def _cells(s: SampleGrid) -> tuple[NDArray, NDArray]:
    """Return the lattice indices (I, J) of sample ``s``'s target grid."""
    return target_lattice_index(s.size, s.res, s.res, s.pos, s.yaw)


def _window_maxima(maps: MapSource, samples: list[SampleGrid], order: list[int], bounds: dict[int, tuple[int, int]],
                   tile: int) -> Iterator[tuple[int, NDArray, NDArray, NDArray]]:
    """Yield (k, I, J, max confidence over sample k's window at its cells) in ``order``
    (time order, window starts not decreasing)."""
    # blocks as long as the shortest window: every window [a, b] is then the suffix
    # [a, end of a's block) plus the prefix [end of a's block, b]
    L = max(min(b - a for a, b in bounds.values()), 1)
    t0 = bounds[order[0]][0]
    t = maps.t_ns
    g_start = 0
    while g_start < len(order):
        kblk = (bounds[order[g_start]][0] - t0) // L
        g_end = g_start
        while g_end < len(order) and (bounds[order[g_end]][0] - t0) // L == kblk:
            g_end += 1
        group = order[g_start:g_end]
        lo, mid = t0 + kblk * L, t0 + (kblk + 1) * L
        # suffix maxima within the block, from its end backwards
        atlas = Atlas(tile, _MAX)
        in_blk = np.nonzero((t >= lo) & (t < mid))[0][::-1]
        pos = 0
        # only the float32 suffix maxima wait for the forward pass (memory: one grid per
        # sample of a window); the lattice indices are cheap to recompute
        suffix: dict[int, NDArray] = {}
        for k in sorted(group, key=lambda k: -bounds[k][0]):
            while pos < len(in_blk) and t[in_blk[pos]] >= bounds[k][0]:
                _max_splat(atlas, maps[int(in_blk[pos])])
                pos += 1
            suffix[k] = atlas.gather(*_cells(samples[k]), ("max",))[0]
        del atlas
        # prefix maxima after the block, forwards; samples leave in time order (= b order)
        atlas = Atlas(tile, _MAX)
        nxt = np.nonzero(t >= mid)[0]
        pos = 0
        for k in group:
            b = bounds[k][1]
            while pos < len(nxt) and t[nxt[pos]] <= b:
                _max_splat(atlas, maps[int(nxt[pos])])
                pos += 1
            I, J = _cells(samples[k])
            yield k, I, J, np.fmax(suffix.pop(k), atlas.gather(I, J, ("max",))[0])
        g_start = g_end
