"""A lazy PyTorch Dataset over the shards: one sample per read, chunk-aligned.

Labels are resampled to the model's grids by nearest cell centre (so any model size
works), elevations are clipped to +-``elevation_clip_m`` and scaled to +-1.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch.utils.data import Dataset

from gtgen import codes
from gtgen.config import TrainConfig
from gtgen.dataset.scans import first_per_voxel
from gtgen.errors import TrainError
from gtgen.geometry import rescale_K
from gtgen.grids import bilinear, filled, nearest_index, point_distance, raw_min_z, smoothed_min_z
from gtgen.storage.dataset import DatasetStore, jpeg_files
from gtgen.train.model import bev_grid


def centre_half_coords(n_src: int, n_dst: int) -> NDArray[np.float64]:
    """Return the coordinates, in source cells (cell i's centre at i), of the centres of
    ``n_dst`` cells spanning exactly the centre half of an ``n_src``-cell grid: the micro
    range inside the short one (for 250 short cells the half starts at 62.5 cells)."""
    return n_src / 4 + (np.arange(n_dst) + 0.5) * (n_src / 2) / n_dst - 0.5


def centre_half_slab(n_src: int) -> tuple[int, int]:
    """Return the smallest cell range [lo, hi) of an ``n_src``-cell grid holding its centre half."""
    return n_src // 4, -(-3 * n_src // 4)


def micro_view(raw: NDArray, n_dst: int) -> NDArray:
    """Return the square grid ``raw`` (n, n) over exactly its centre half at ``n_dst`` cells,
    each taking the source cell its centre lies in (NaN stays NaN)."""
    ix = np.clip(np.floor(centre_half_coords(raw.shape[0], n_dst) + 0.5).astype(np.int64), 0, raw.shape[0] - 1)
    return raw[np.ix_(ix, ix)]


def _unless_identity(ix: NDArray, n: int) -> NDArray | None:
    """Return the cell indices ``ix`` into a grid of ``n`` cells a side, or None when they
    take every cell in order."""
    return None if len(ix) == n and (ix == np.arange(n)).all() else ix


def decode_at(jpeg: bytes, width: int, height: int) -> tuple[NDArray[np.uint8], tuple[int, int]]:
    """Return a JPEG file decoded and resized to width x height (H, W, 3) RGB, and the
    source extent (width, height) [px of the stored image] the result spans, for
    ``rescale_K``. A smaller size is decoded at 1/2, 1/4 or 1/8 scale first (libjpeg's DCT
    scaling, which costs a fraction of a full decode), then resized (antialiased
    bilinear): the extent is then that of the scaled decode's whole blocks."""
    from PIL import Image

    try:
        with Image.open(io.BytesIO(jpeg)) as img:
            w, h = img.size
            img.draft("RGB", (width, height))
            f = max(1, int(round(w / img.size[0])))
            src = (img.size[0] * f, img.size[1] * f) if f > 1 else (w, h)
            img = img.convert("RGB")
            if img.size != (width, height):
                img = img.resize((width, height), Image.BILINEAR)
            return np.asarray(img), src
    except Exception as err:  # noqa: BLE001 - PIL raises several types
        raise TrainError(f"a stored JPEG of {len(jpeg)} bytes does not decode ({err}); rebuild the dataset") from err


def for_dataset(tc: TrainConfig, cameras: list[str], where: str) -> TrainConfig:
    """Return ``tc`` with the camera input off when the dataset at ``where`` holds no
    camera (``cameras`` empty), saying so in one log line; raise TrainError when the
    cameras are the model's only input."""
    if cameras or not tc.cameras:
        return tc
    if not (tc.points or tc.raw_elevation):
        raise TrainError(f"dataset '{where}' holds no camera images, and the cameras are the model's only input "
                         "(train.points and raw_elevation are off); turn one of them on")
    import logging

    logging.getLogger(__name__).warning("dataset '%s' holds no camera images: the camera input is off (train.cameras: false)", where)
    return tc.model_copy(update={"cameras": False})


def camera_mismatch(trained: list[str], dataset: list[str], ckpt: Path, where: Path) -> TrainError | None:
    """Return the error for a checkpoint whose image branch was trained on the cameras
    ``trained`` evaluated on a dataset of the cameras ``dataset`` (None when they are the same)."""
    if trained == dataset:
        return None
    return TrainError(f"checkpoint '{ckpt}' was trained on the cameras {trained}; dataset '{where}' has {dataset}: evaluate it on a "
                      "dataset of the same camera rig (or train on this one)")


# why a dataset cannot give the N-scan input, and how to get it
NO_SCANS = ("holds no raw lidar scans, which train.geometry: scans reads (Tab. III's N-scan input); map the bags' PointCloud2 "
            "scans to the lidar role (topics.lidar) and rebuild it with gtgen extract, fuse and dem-align")


class ShardDataset(Dataset):
    """Samples of a dataset store as tensors, at the model sizes of a ``TrainConfig``.

    Works with a ``torch.utils.data.DataLoader`` and any number of workers (each opens the
    store itself); stack samples with ``gtgen.train.network.collate`` or the default
    collate. ``ds[i]`` is a dict of tensors (n_m / n_s = ``tc.micro_size`` / ``short_size``,
    n_b the BEV grid's cells: ``model.bev_grid``; labels resampled by nearest cell centre;
    elevations relative to the base height at t). Only what the model takes is read: no
    images without ``tc.cameras``, no points without ``tc.points``, no raw / prior grids
    without ``tc.raw_elevation``, the ``<r>/`` keys of the ranges it predicts only, and
    the evaluation's baselines (``<r>/xr_*``, ``<r>/raw_elevation``) only with
    ``baselines`` (training reads without them: the loss never does):

    ===========================  ======================  ==========================================
    key                          shape, dtype            meaning
    ===========================  ======================  ==========================================
    index                        (), int64               dataset sample index
    images                       (C, 3, H, W), uint8     the C cameras' (the dataset's attribute cameras)
                                                         RGB bytes decoded from the stored JPEG at
                                                         the model's size (the model normalises
                                                         them: ``model.normalize_images``)
    K                            (C, 3, 3), float32      intrinsics at the model's image size [px]
    T_target_cam                 (C, 4, 4), float32      target <- camera optical [m]
    points, n_points             (P, 3) float32, ()      voxel points (train.geometry: scans, the
                                                         last n_scans scans) in the target frame
                                                         [m], the first n_points valid (P =
                                                         max_points, default shards.max_voxel_points
                                                         / the stored N-scan input's points)
    raw                          (2, n_b, n_b), float32  min-z per BEV cell / elevation_clip_m
                                                         (0 where none), and its validity (0/1);
                                                         of the scans with train.geometry: scans
    prior, prior_micro           (2, n, n), float32      smoothed min z filled everywhere (scaled
                                                         like raw), distance to the nearest cell
                                                         with points / grid size; over the BEV
                                                         grid / the micro grid (micro predicted)
    <r>/elevation                (n_r, n_r), float32     label / elevation_clip_m (NaN: no label)
    <r>/risk                     (n_r, n_r), float32     label risk 0..1 (NaN: none)
    <r>/region                   (n_r, n_r), uint8       gtgen.codes: 0 none, 1 obs PC, 2 obs F, 3 unobs
    <r>/xr_elevation, xr_risk    (n_r, n_r), float32     X-Racer's map at t [m] / 0..1 (NaN: none);
                                                         with ``baselines``
    <r>/raw_elevation            (n_r, n_r), float32     min z [m] (NaN where no point); with ``baselines``
    ===========================  ======================  ==========================================
    """

    def __init__(self, path: Path, tc: TrainConfig, split: str | None = None, max_points: int | None = None,
                 baselines: bool = True) -> None:
        store = DatasetStore(path)
        if store.n_samples == 0:
            raise TrainError(f"dataset '{path}' has no samples; nothing to train or evaluate on")
        self.path = path
        self.tc = tc
        self.data_cfg = store.config
        self.store = store
        self.baselines = baselines
        self.scans = tc.points and tc.geometry == "scans"
        if self.scans and not store.has_scans:
            raise TrainError(f"dataset '{path}' {NO_SCANS}")
        if tc.cameras and not store.cameras:
            raise TrainError(f"dataset '{path}' holds no camera images; train with train.cameras: false")
        if self.scans and tc.n_scans > store.scan_dims[1]:
            raise TrainError(f"train.n_scans = {tc.n_scans}, but dataset '{path}' stores the last {store.scan_dims[1]} scans "
                             "(shards.max_scans); expected at most that, or rebuild it with a larger shards.max_scans")
        idx = np.arange(store.n_samples)
        if split is not None:
            code = codes.split_code(split)
            idx = idx[store.meta("split") == code]
        self.indices = idx
        # every stored point by default (the store keeps at most shards.max_voxel_points):
        # PointPillars caps pillars, not points
        self.max_points = max_points or (store.scan_dims[0] if self.scans else self.data_cfg.shards.max_voxel_points)
        self._r: dict | None = None
        self._offsets = store.voxel_offsets()
        # the cells of each stored grid the model's grid takes (None: the stored grid itself)
        self._ix = {r: _unless_identity(nearest_index(store.size(r), getattr(tc, f"{r}_size")), store.size(r)) for r in ("micro", "short")}
        bev_m, self._bev_size = bev_grid(tc, self.data_cfg.grids)
        # smoothing window of each range's prior, in that range's model cells (odd)
        grids = self.data_cfg.grids
        cells = {"micro": grids.micro.length_m / tc.micro_size, "bev": bev_m / self._bev_size}
        cells["centre"] = grids.short.length_m / store.size("short")  # the stored raw grid's own cells
        self._prior_win = {r: 2 * int(round(0.5 * tc.prior_window_m / c)) + 1 for r, c in cells.items()}

    def _scaled(self, grid: NDArray) -> torch.Tensor:
        """Return (2, n, n): the elevation clipped and scaled to +-1 (0 where NaN), and its validity."""
        clip = self.tc.elevation_clip_m
        return torch.from_numpy(np.stack([np.nan_to_num(np.clip(grid, -clip, clip) / clip), np.isfinite(grid)]).astype(np.float32))

    def _prior(self, grid: NDArray, window: int) -> NDArray[np.float32]:
        """Return (2, n, n): the min-z ``grid`` smoothed over ``window`` cells and filled
        everywhere, scaled like "raw", and the distance to the nearest cell with points / n."""
        clip = self.tc.elevation_clip_m
        return np.stack([np.clip(filled(smoothed_min_z(grid, window)), -clip, clip) / clip, point_distance(grid)]).astype(np.float32)

    def _micro_prior(self, raw_s: NDArray) -> NDArray[np.float32]:
        """Return the micro prior (2, m, m) of the stored min-z grid ``raw_s`` computed at its
        own resolution on the cells holding its centre half (one more for an odd half: 126 of
        250), then sampled bilinearly at the micro cells' centres."""
        n_s = raw_s.shape[0]
        lo, hi = centre_half_slab(n_s)
        prior = self._prior(raw_s[lo:hi, lo:hi], self._prior_win["centre"])
        x = centre_half_coords(n_s, self.tc.micro_size) - lo
        return bilinear(prior, x[:, None], x[None, :], outside="edge").astype(np.float32)

    def __len__(self) -> int:
        return len(self.indices)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_r": None}  # each DataLoader worker makes its own readers

    def _readers(self) -> dict[Any, Any]:
        """Return the readers of the arrays a sample needs, made lazily in each DataLoader
        worker (per-sample arrays one shard-file read each, the flat points by range)."""
        if self._r is None:
            st = self.store
            self._r = {n: st.inputs(n) for n in ("T_target_base", "raw_elevation_m") + (("jpeg", "jpeg_nbytes", "K", "T_base_cam") if self.tc.cameras else ())}
            self._r["points"] = st.voxel_points()
            if self.scans:
                self._r["scan_points"], self._r["scan_counts"] = st.scan_input()
            grids = [("labels", "elevation_m"), ("labels", "risk"), ("labels", "region")]
            grids += [("xracer", "elevation_m"), ("xracer", "risk")] if self.baselines else []
            self._r.update({(kind, r, a): st.grid(kind, r, a) for r in self.tc.predicted_ranges for kind, a in grids})
        return self._r

    def _images(self, files: list[bytes], K: NDArray) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
        """Return the cameras' images decoded at the model's size, as (n, 3, h, w) bytes, and
        their intrinsics (n, 3, 3) at that size; ``gtgen.train.model.normalize_images``
        makes the network's floats on the device."""
        W, H = self.tc.image_width, self.tc.image_height
        imgs, Ks = [], []
        for f, Kc in zip(files, K):
            img, src = decode_at(f, W, H)
            imgs.append(img)
            Ks.append(rescale_K(Kc, src, (W, H)))
        return np.ascontiguousarray(np.stack(imgs).transpose(0, 3, 1, 2)), np.stack(Ks)

    def _grid(self, arr: NDArray, rng: str) -> NDArray:
        ix = self._ix[rng]
        return arr if ix is None else arr[np.ix_(ix, ix)]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        g = self._readers()
        k = int(self.indices[i])
        tc = self.tc
        out: dict[str, torch.Tensor] = {"index": torch.tensor(k)}
        if tc.cameras:
            imgs, K = self._images(jpeg_files(g["jpeg"][k], g["jpeg_nbytes"][k]), g["K"][k])
            out["images"] = torch.from_numpy(imgs)
            out["K"] = torch.from_numpy(K.astype(np.float32))
            T = g["T_target_base"][k] @ g["T_base_cam"][k]
            out["T_target_cam"] = torch.from_numpy(T.astype(np.float32))
        scan_pts = self._scan_points(g, k) if self.scans else None
        if tc.points:
            pts = scan_pts if scan_pts is not None else g["points"](self._offsets[k], self._offsets[k + 1])
            if len(pts) > self.max_points:
                pts = pts[np.linspace(0, len(pts) - 1, self.max_points).astype(np.int64)]
            padded = np.zeros((self.max_points, 3), np.float32)
            padded[: len(pts)] = pts
            out["points"] = torch.from_numpy(padded)
            out["n_points"] = torch.tensor(len(pts))
        ranges = tc.predicted_ranges
        for r in ranges:
            el = self._grid(g[("labels", r, "elevation_m")][k], r)
            out[f"{r}/elevation"] = torch.from_numpy((np.clip(el, -tc.elevation_clip_m, tc.elevation_clip_m) / tc.elevation_clip_m).astype(np.float32))
            out[f"{r}/risk"] = torch.from_numpy(self._grid(g[("labels", r, "risk")][k], r).astype(np.float32))
            out[f"{r}/region"] = torch.from_numpy(np.ascontiguousarray(self._grid(g[("labels", r, "region")][k], r), np.uint8))
            if self.baselines:
                out[f"{r}/xr_elevation"] = torch.from_numpy(self._grid(g[("xracer", r, "elevation_m")][k], r).astype(np.float32))
                out[f"{r}/xr_risk"] = torch.from_numpy(self._grid(g[("xracer", r, "risk")][k], r).astype(np.float32))
        # the raw min-z grid is short range (the evaluation's raw baselines read it too); its
        # micro view is exactly its centre half
        stored = g["raw_elevation_m"][k] if tc.raw_elevation or self.baselines else None
        if tc.raw_elevation:
            n_s = stored.shape[0]
            # the N-scan input replaces the voxel map in the network's inputs (not in the baselines)
            raw_s = stored if scan_pts is None else raw_min_z(scan_pts, n_s, self.data_cfg.grids.short.length_m / n_s)
            # the priors the heads correct, each grid at its own resolution, scaled like "raw":
            # (smoothed min z filled everywhere, distance to the nearest cell with points)
            bev = self._grid(raw_s, "short") if tc.ranges != "micro" else micro_view(raw_s, self._bev_size)
            out["raw"] = self._scaled(bev)
            out["prior"] = torch.from_numpy(self._prior(bev, self._prior_win["bev"]))
            if "micro" in ranges:
                fine = tc.micro_size > n_s // 2  # finer than the points' grid: computed on it, then resampled
                out["prior_micro"] = torch.from_numpy(self._micro_prior(raw_s) if fine else
                                                      self._prior(micro_view(raw_s, tc.micro_size), self._prior_win["micro"]))
        if self.baselines:
            for r in ranges:
                grid = micro_view(stored, tc.micro_size) if r == "micro" else self._grid(stored, "short")
                out[f"{r}/raw_elevation"] = torch.from_numpy(grid.astype(np.float32))
        return out

    def _scan_points(self, g: dict, k: int) -> NDArray[np.float32]:
        """Return sample ``k``'s last ``n_scans`` scans (a prefix of the stored N-scan input),
        voxel-filtered again when ``train.scan_voxel_m`` is not the stored filter's edge."""
        n = int(g["scan_counts"][k][self.tc.n_scans - 1])
        pts = g["scan_points"][k][:n]
        if self.tc.scan_voxel_m != self.data_cfg.shards.scan_voxel_m:
            pts = pts[first_per_voxel(pts, self.tc.scan_voxel_m)]
        return pts
