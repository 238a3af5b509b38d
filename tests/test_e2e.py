"""The user's own words, verbatim, in one folder: synth -> extract -> fuse -> dem-align -> train -> eval."""

from __future__ import annotations

import numpy as np

from bagtools import split_mcap
from conftest import run_cli


def test_users_commands_verbatim_in_one_folder(tmp_path):
    steps = [
        ("synth", "drive", "--duration", "2", "--format", "mcap"),
        ("extract", "drive/drive.mcap"),
        ("fuse", "--window", "60"),
        ("dem-align",),
        ("train", "--steps", "1"),
        ("eval", "--split", "all"),  # a 2 s drive has no val block: an empty val split is an error
    ]
    for args in steps:
        p = run_cli(*args, cwd=tmp_path)
        assert p.returncode == 0, f"gtgen {' '.join(args)} failed:\n{p.stderr}"
    ws = tmp_path / "gtgen_ws"
    import warnings

    import zarr

    for name in ("drive.zarr", "fused.zarr", "dataset.zarr"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # only Zarr objects inside a store: opening it warns of nothing
            g = zarr.open_group(str(ws / name), mode="r")
            assert g.attrs["config"]["grids"]["micro"]["size"] > 0  # the resolved config lives in the attributes
            list(g.members(max_depth=None))
    assert (tmp_path / "runs" / "tiny" / "ckpt.pt").is_file() and (tmp_path / "runs" / "latest").is_symlink()
    assert (tmp_path / "drive" / "gtgen-config.yaml").is_file()


def test_a_drive_split_into_two_bags_equals_one_bag(drive_dir, drive_store, cfg, tmp_path):
    from gtgen.extract import run_extract
    from gtgen.storage.drive import DriveStore

    a, b = split_mcap(drive_dir / "drive.mcap", tmp_path / "part_0.mcap", tmp_path / "part_1.mcap", 4.0)
    run_extract([a, b], tmp_path / "two.zarr", cfg, workers=1)
    x, y = DriveStore(drive_store).group, DriveStore(tmp_path / "two.zarr").group
    for name in ("samples/t_ns", "poses/t_ns", "maps/short/t_ns", "samples/jpeg"):
        np.testing.assert_array_equal(x[name][:], y[name][:], err_msg=name)


def test_dem_align_rerun_with_other_workers_gives_the_same_dataset(dataset, drive_store, fused_store, cfg, tmp_path):
    """The fixture's dataset (2 workers, each shard built as soon as the ICP chain has
    placed it) is the oracle's byte for byte: 1 worker, every shard built after the chain."""
    from conftest import assert_same_store
    from gtgen.dataset.dem_align import run_dem_align

    run_dem_align(drive_store, fused_store, None, tmp_path / "again.zarr", cfg, workers=1, stream=False)
    assert_same_store(dataset, tmp_path / "again.zarr")
