"""Merge drives' datasets into one, drive after drive, as their samples' shard bytes."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from gtgen import codes
from gtgen.config import GtgenConfig
from gtgen.dataset.dem_align import dataset_attrs
from gtgen.errors import GtgenError
from gtgen.runtime.output import atomic_output
from gtgen.storage.dataset import DatasetStore
from gtgen.storage.dataset_writer import ShardWriter
from gtgen.storage.schema import DatasetAttrs, DriveEntry


class DatasetMerger:
    """Appends each drive's dataset to the partial dataset at ``tmp`` in turn, reading
    whole shards at a time; ``finish`` writes the attributes."""

    FIRST_CAPACITY = 1024  # samples; the writer grows the arrays as drives arrive

    def __init__(self, tmp: Path, cfg: GtgenConfig) -> None:
        self.tmp, self.cfg = tmp, cfg
        self.writer: ShardWriter | None = None
        self.drives: list[DriveEntry] = []
        self._first: DatasetAttrs | None = None

    def add(self, name: str, dataset: Path, split: str | None = None) -> int:
        """Append the samples of the dataset at ``dataset`` as drive ``name``, all of them
        in ``split`` if given (``test``: the drive held out whole), else in the geography
        split they have; return how many."""
        src = DatasetStore(dataset)
        if self.writer is None:
            self.writer = ShardWriter(self.tmp, self.FIRST_CAPACITY, self.cfg.grids.micro.size, self.cfg.grids.short.size,
                                      len(src.cameras), src.jpeg_capacity, scans=src.scan_dims, precision=self.cfg.shards.precision,
                                      qa_ranges=self.cfg.shards.qa_ranges)
            self._first = src.info
        elif src.cameras != self._first.cameras:
            raise GtgenError(f"drive {name!r} has the cameras {src.cameras}, the drives before it {self._first.cameras}: a dataset "
                             "holds one camera rig; build the drives of each rig into their own dataset")
        elif src.jpeg_capacity != self.writer.jpeg_capacity:
            raise GtgenError(f"drive {name!r} stores images of up to {src.jpeg_capacity} bytes, the drives before it "
                             f"{self.writer.jpeg_capacity}: build every drive with the same extract.image_width and image_height")
        code = None if split is None else codes.split_code(split)
        n = self.writer.append_dataset(src, len(self.drives), f"build: merging {name}", split=code)
        self.drives += [d.model_copy(update={"name": name}) for d in src.info.drives]
        return n

    def finish(self, provenance: dict | None = None) -> tuple[int, dict[str, int]]:
        """Write the merged dataset's attributes; return (samples, split counts)."""
        if self.writer is None or self._first is None:
            raise GtgenError("no drive to merge: every drive failed")
        n = self.writer.close(dataset_attrs(self.cfg, self.drives, self._first.image_size, self._first.cameras, provenance))
        return n, self.writer.split_counts()


@contextlib.contextmanager
def merging(path: Path, cfg: GtgenConfig, overwrite: bool = False) -> Iterator[DatasetMerger]:
    """Yield a merger whose dataset appears at ``path`` only when the block succeeds (call
    ``finish`` inside it). Use inside a held lock of ``path``."""
    with atomic_output(path, overwrite) as tmp:
        yield DatasetMerger(tmp, cfg)
