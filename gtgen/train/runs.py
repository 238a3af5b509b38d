"""Results tied to their inputs: what a run folder, an evaluation and an experiments
folder record of the dataset they were computed on, and the check before one is reused.

The record is the dataset's path as given and its identity (``storage.integrity.identity``:
a hash of what its manifest records of its arrays, so a rebuild of the same data keeps it).
A checkpoint and ``metrics.json`` carry it under ``dataset``; so do ``eval.json`` and
``experiments.json``. A run is resumed, and a run or an evaluation reused, only on the
dataset it records; anything else is one line naming both datasets and what to do.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from gtgen.errors import TrainError

METRICS = "metrics.json"


def dataset_record(store: Any) -> dict[str, str]:
    """Return the record of the dataset ``store`` (a ``DatasetStore``): its path and identity."""
    return {"path": str(store.path), "identity": store.identity}


def recorded_dataset(run_dir: Path) -> dict | None:
    """Return the dataset record of the run in ``run_dir`` (its metrics, else its checkpoint;
    None when it has neither, or they record none: an earlier gtgen's)."""
    try:
        rec = json.loads((run_dir / METRICS).read_text()).get("dataset")
        if rec is not None:
            return rec
    except (OSError, ValueError, AttributeError):
        pass
    ckpt = run_dir / "ckpt.pt"
    if not ckpt.is_file():
        return None
    from gtgen.train.checkpoint import load_checkpoint

    return load_checkpoint(ckpt)[0].get("dataset")


def describe(rec: dict | None) -> str:
    """Return a record as words: "dataset 'a/dataset.zarr' (identity 1f2e...)"."""
    if not rec:
        return "a dataset it does not record (an earlier gtgen's run)"
    return f"dataset '{rec.get('path')}' (identity {rec.get('identity')})"


def same_dataset(rec: dict | None, store: Any) -> bool:
    """Whether the record ``rec`` is of the dataset ``store``."""
    return bool(rec) and rec.get("identity") == store.identity


def check_resume(state: dict, store: Any, run_dir: Path) -> None:
    """Raise TrainError unless the checkpoint ``state`` of ``run_dir`` was trained on ``store``."""
    rec = state.get("dataset")
    if not same_dataset(rec, store):
        raise TrainError(f"--resume: run '{run_dir}' was trained on {describe(rec)}, not on {describe(dataset_record(store))}; "
                         "resume it on its own dataset, or train a new run (another --run-dir)")
