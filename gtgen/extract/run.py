"""``gtgen extract``: bags -> a time-indexed per-drive store, in one read of the bags.

``run_extract`` reads like its steps: open the bags, resolve the roles and read the
static frames, read the bags in record-time slices on the pool (each slice staging what
the plan will likely keep), merge the slices, build the TF buffer and the pose track,
drop what no transform places in odom, select the samples, and write the store.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gtgen import __version__, codes
from gtgen.bag.reader import BagSet, hash_bag
from gtgen.config import RANGES, GtgenConfig
from gtgen.errors import BagError
from gtgen.extract import calib, mapped
from gtgen.extract.images import stored_cameras
from gtgen.extract.inventory import Scan, merged
from gtgen.extract.roles import mapping_topics, reference_role, resolve_roles
from gtgen.extract.scan import Frames, import_readers, prepass, scan_slice, slices
from gtgen.extract.select import Plan, select
from gtgen.extract.write import Slices, write_large, write_small
from gtgen.runtime.output import stage_output
from gtgen.runtime.pool import Pool
from gtgen.storage.drive import DriveWriter


@dataclass
class ExtractResult:
    """What an extract did: the store, per-topic stats, sample counts by reason."""

    store: Path
    topics: list[dict]
    n_candidates: int
    n_samples: int
    rejected: dict[str, int]
    maps_kept: dict[str, int]
    skew_s: dict[str, float]
    warnings: list[str]
    poses: str = ""  # where the poses came from
    reread: int = 0  # kept messages no slice had staged, read in a second pass
    reference: str = ""  # the sensor sample times snap to (extract.reference), and its topic
    bag_sha256: list[str] = field(default_factory=list)  # of each bag, in the order given

    def report(self) -> dict[str, Any]:
        """Return the report stored in the drive store's attributes."""
        return {"topics": self.topics, "n_candidates": self.n_candidates, "n_samples": self.n_samples,
                "rejected": self.rejected, "maps_kept": self.maps_kept, "skew_s": self.skew_s,
                "poses": self.poses, "reread": self.reread, "warnings": self.warnings}


def run_extract(paths: list[Path], out: Path, cfg: GtgenConfig, workers: int = 2, n_slices: int | None = None,
                staging: bool = True, bag_sha256: list[str] | None = None, overwrite: bool = False) -> ExtractResult:
    """Read the bags of one drive into the drive store ``out`` (written atomically).

    The bags are read as record-time slices on ``workers`` processes (``n_slices`` fixes
    their number, for tests), once: each slice stages what the plan will likely keep.
    ``staging=False`` stages nothing and reads the kept messages in a second pass (the
    two-pass reference). The store depends on none of the three. ``bag_sha256``, the
    bags' hashes if the caller has them already, spares hashing them again. An existing
    ``out`` that gtgen did not write is replaced only with ``overwrite``.
    """
    if bag_sha256 is not None and len(bag_sha256) != len(paths):
        raise ValueError(f"{len(bag_sha256)} bag hashes given for {len(paths)} bags")
    with stage_output(out, reads=paths, overwrite=overwrite) as tmp, Pool(workers, warm=import_readers) as pool, \
            ThreadPoolExecutor(max_workers=1) as hasher:  # hashing releases the GIL: it overlaps the read
        roles, bounds, frames, lidar = _open(paths, cfg, workers, n_slices)
        hashes = [hasher.submit(hash_bag, p) for p in paths] if bag_sha256 is None else []
        w = DriveWriter(tmp)  # before the read: the slices stage into it
        scan, parts = _read(pool, paths, cfg, roles, frames, bounds, tmp if staging else None)
        tf = calib.tf_buffer(cfg, scan)
        track, poses, warnings = calib.pose_track(cfg, scan, tf)
        calib.drop_untransformable(cfg, scan, tf)
        mapped.declare(cfg, scan)
        plan = _plan(cfg, track, scan)
        cams = stored_cameras(cfg, scan.info)
        write_small(w, scan, track, plan, cams, *calib.extrinsics(cfg, scan, tf, plan.image_t, cams))
        reread = write_large(w, paths, cfg, roles, scan, tf, track, plan, parts, pool, lidar, cams)
        result = _result(out, scan, plan, scan.warnings + warnings, reread, bag_sha256, hashes)
        result.poses = poses
        ref = reference_role(cfg, roles.values())
        what = f"camera '{ref.split('.')[1]}'" if ref.startswith("camera.") else "the lidar"
        result.reference = f"{what} on '{_topic(roles, ref)}'"
        _finish(w, paths, cfg, result)
    return result


def _topic(roles: dict[str, str], role: str) -> str:
    return next(t for t, r in roles.items() if r == role)


def _open(paths: list[Path], cfg: GtgenConfig, workers: int, n_slices: int | None) -> tuple[dict[str, str], list, Frames, list[str]]:
    """Open the bags once: the roles of their topics, the read's slices, the static frames,
    and the raw-scan topics the mapping reads (none when every map comes from the bags)."""
    with BagSet(paths) as bags:
        topics = bags.topics()
        roles = resolve_roles(cfg, topics)
        lidar = mapping_topics(cfg, topics)
        frames = prepass(bags, cfg, {**roles, **dict.fromkeys(lidar, "lidar.map")})
        return roles, slices(bags, workers, n_slices), frames, lidar


def _read(pool: Pool, paths: list[Path], cfg: GtgenConfig, roles: dict[str, str], frames: Frames, bounds: list,
          stage: Path | None) -> tuple[Scan, Slices]:
    """Read every slice on the pool; return the merged scan and the slices' parts."""
    jobs = [(paths, cfg, roles, frames, a, b, None if stage is None else str(stage), k) for k, (a, b) in enumerate(bounds)]
    parts = list(pool.map(scan_slice, jobs, "extract: reading"))
    slices_ = Slices(bounds, [p.counts() for p in parts], [p.staged for p in parts] if stage is not None else [])
    scan = merged(parts)  # after the counts above: the merge grows parts[0]
    scan.require_usable()
    return scan, slices_


def _plan(cfg: GtgenConfig, track: Any, scan: Scan) -> Plan:
    plan = select(cfg, track, scan)
    if len(plan.t) == 0:
        raise BagError(f"no sample passed selection out of {len(plan.cand_t)} candidates: {codes.reason_counts(plan.cand_reason)}")
    return plan


def _result(out: Path, scan: Scan, plan: Plan, warnings: list[str], reread: int, bag_sha256: list[str] | None,
            hashes: list[Future]) -> ExtractResult:
    return ExtractResult(
        store=out, topics=[s.summary() for s in scan.stats.values()], n_candidates=len(plan.cand_t), n_samples=len(plan.t),
        rejected=codes.reason_counts(plan.cand_reason), maps_kept={r: len(plan.map_t[r]) for r in RANGES},
        skew_s=plan.skews(), warnings=warnings, reread=reread, bag_sha256=bag_sha256 or [h.result() for h in hashes],
    )


def _finish(w: DriveWriter, paths: list[Path], cfg: GtgenConfig, result: ExtractResult) -> None:
    """Write the store's attributes (last: they mark it complete; the resolved config is one)."""
    w.complete(
        gtgen_version=__version__,
        bags=[{"path": str(p.resolve()), "sha256": h} for p, h in zip(paths, result.bag_sha256)],
        config=cfg.model_dump(mode="json"), report=result.report(), reasons=codes.REASONS,
        image_size=[cfg.extract.image_width, cfg.extract.image_height], cameras=cfg.topics.camera_names,
    )
