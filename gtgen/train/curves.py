"""Training curves: TensorBoard event files (``<run>/tb/``) and CSV tables of every logged
step (``<run>/train.csv``: losses, learning rate, data-wait and step time) and of every
validation (``<run>/val.csv``). On ``--resume`` the rows and events after the checkpoint's
step (those of the killed run) are dropped, so the curves continue where the weights do.
"""

from __future__ import annotations

import csv
from pathlib import Path

from gtgen.runtime.output import write_atomic


class Curves:
    """The run's curve writers (rank 0 only)."""

    def __init__(self, run_dir: Path, resume_step: int | None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.files = {"train": run_dir / "train.csv", "val": run_dir / "val.csv"}
        if resume_step is None:
            for f in self.files.values():
                f.unlink(missing_ok=True)
        else:
            for f in self.files.values():
                _truncate(f, resume_step)
        self.tb = SummaryWriter(str(run_dir / "tb"), purge_step=None if resume_step is None else resume_step + 1)

    def log(self, kind: str, step: int, values: dict[str, float]) -> None:
        """Append one row of ``kind`` (train / val) and its TensorBoard scalars."""
        f = self.files[kind]
        new = not f.is_file() or f.stat().st_size == 0
        with f.open("a", newline="") as fh:
            w = csv.writer(fh)
            if new:
                w.writerow(["step", *values])
            w.writerow([step, *(f"{v:.6g}" for v in values.values())])
        for k, v in values.items():
            self.tb.add_scalar(f"{kind}/{k}", v, step)

    def close(self) -> None:
        self.tb.close()


def _truncate(path: Path, step: int) -> None:
    """Keep the header and the rows of ``path`` up to ``step``."""
    if not path.is_file():
        return
    lines = path.read_text().splitlines(keepends=True)
    keep = lines[:1] + [ln for ln in lines[1:] if ln.split(",", 1)[0].isdigit() and int(ln.split(",", 1)[0]) <= step]
    write_atomic(path, "".join(keep), overwrite=True)  # the run's own table, in the run folder it holds locked


def read_csv(path: Path) -> list[dict[str, float]]:
    """Return the rows of a curve table as dicts of floats."""
    with path.open(newline="") as fh:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(fh)]
