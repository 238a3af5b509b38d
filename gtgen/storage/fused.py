"""The fused store (``gtgen fuse``): read by name through :class:`FusedStore`, written
through :class:`FusedWriter`. Arrays and units: ``schema.FUSED`` and data_schema.md."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gtgen.config import RANGES, GtgenConfig, stored_config
from gtgen.errors import StoreError
from gtgen.storage.chunks import ChunkFiles
from gtgen.storage.schema import FUSED, FUSED_QA
from gtgen.storage.stores import Rows, Store, StoreWriter

# per range: the fused label layers, and X-Racer's map at t; one (S, n, n) array each
# (the QA ones, ``schema.FUSED_QA``, only for the store's ``qa_ranges``)
LABEL_LAYERS = ("elevation_m", "confidence", "risk", "count", "last_dt_s", "region")
XRACER_LAYERS = ("elevation_m", "risk", "confidence")
KINDS = {"fused": LABEL_LAYERS, "xracer": XRACER_LAYERS}


def layers(kind: str, rng: str, qa_ranges: Any) -> tuple[str, ...]:
    """Return the layers of ``kind`` a fused store holds for range ``rng`` when it holds
    the QA grids of ``qa_ranges``."""
    return tuple(x for x in KINDS[kind] if rng in qa_ranges or x not in FUSED_QA[kind])


@dataclass
class FusedSample:
    """One sample's fused grids per range: ``labels[r][layer]`` and ``xracer[r][layer]``,
    as values, or as stored chunks (``chunks.Encoded``) where asked to pass them through."""

    labels: dict[str, dict[str, Any]]
    xracer: dict[str, dict[str, Any]]


class FusedStore(Store):
    """A complete fused store, read by name."""

    fmt = FUSED

    @cached_property
    def config(self) -> GtgenConfig:
        """The config the store was fused with (its train section left out)."""
        return stored_config(self.attrs.get("config", {}), f"fused store '{self.path}'", self.fmt.config_sections)

    @property
    def n_samples(self) -> int:
        """Samples of the drive (fused or not)."""
        return self.shape("samples/reason")[0]

    def size(self, rng: str) -> int:
        """Return the cells per side of range ``rng``'s grids."""
        return self.shape(f"fused/{rng}/region")[1]

    @property
    def qa_ranges(self) -> list[str]:
        """The ranges whose QA grids the store holds (``shards.qa_ranges`` when fused)."""
        return list(self.attrs["qa_ranges"])

    def reason(self) -> NDArray[np.uint8]:
        """Return per sample 0 (fused) or why not (``gtgen.codes``)."""
        return self.read("samples/reason")

    def grid(self, rng: str, layer: str) -> Rows:
        """Return the reader of fused label layer ``layer`` (``LABEL_LAYERS``) of range ``rng``
        (``reader[k]``: sample k's grid in its target frame)."""
        return self._rows("fused", rng, layer)

    def _rows(self, kind: str, rng: str, layer: str) -> Rows:
        if layer not in KINDS[kind]:
            raise KeyError(f"{kind} layer {layer!r} unknown; expected one of {list(KINDS[kind])}")
        if layer not in layers(kind, rng, self.qa_ranges):
            raise StoreError(f"fused store '{self.path}' holds no {kind} {rng} {layer} (a QA grid: it was fused with "
                             f"shards.qa_ranges {self.qa_ranges}); run 'gtgen fuse' again with {rng} in shards.qa_ranges")
        key = f"{kind}/{rng}/{layer}"
        cache = self.__dict__.setdefault("_readers", {})
        if key not in cache:
            cache[key] = self.rows(key)
        return cache[key]

    def sample(self, k: int, decode: set[tuple[str, str]] = frozenset()) -> FusedSample:
        """Return sample ``k``'s grids; the label layers (range, layer) in ``decode`` as values,
        everything else as stored (a chunk that can move into the dataset as it is)."""
        out = FusedSample({r: {} for r in RANGES}, {r: {} for r in RANGES})
        for r in RANGES:
            for kind, dest in (("fused", out.labels), ("xracer", out.xracer)):
                for layer in layers(kind, r, self.qa_ranges):
                    rows = self._rows(kind, r, layer)
                    dest[r][layer] = rows[k] if kind == "fused" and (r, layer) in decode else rows.encoded(k)
        return out


class FusedWriter(StoreWriter):
    """A fused store being written, one sample's grids at a time (one chunk each)."""

    fmt = FUSED

    def __init__(self, path: Path, new: bool = True) -> None:
        super().__init__(path, new)
        self._files: dict[str, ChunkFiles] = {}
        self.qa_ranges: list[str] = []

    @classmethod
    def reopen(cls, path: Path) -> FusedWriter:
        """Return the writer of a fused store being written (in another process)."""
        return cls(path, new=False)

    def create_grids(self, n_samples: int, sizes: dict[str, int], qa_ranges: Any = RANGES) -> None:
        """Create every range's per-sample grids (``sizes``: cells per side per range), the
        QA grids only for ``qa_ranges``."""
        self.qa_ranges = [r for r in RANGES if r in qa_ranges]
        for kind in KINDS:
            for r in RANGES:
                n = sizes[r]
                for layer in layers(kind, r, qa_ranges):
                    self.create(f"{kind}/{r}/{layer}", (n_samples, n, n), chunks=(1, n, n), flat=True)

    def write_sample(self, rng: str, k: int, labels: dict[str, NDArray], xracer: dict[str, NDArray]) -> None:
        """Write sample ``k``'s fused ``labels`` and X-Racer ``xracer`` grids of range ``rng``
        by layer (those the store holds, ``layers``: an array it does not hold is a KeyError)."""
        for kind, values in (("fused", labels), ("xracer", xracer)):
            for layer in (x for x in KINDS[kind] if x in values):
                key = f"{kind}/{rng}/{layer}"
                if key not in self._files:
                    self._files[key] = ChunkFiles(self.root[key])
                self._files[key].write(k, values[layer])

    def finish(self, reason: NDArray[np.uint8], **attrs: Any) -> None:
        """Write why each sample is not fused (0: fused) and complete the store, recording
        the ranges whose QA grids it holds (``qa_ranges``)."""
        self.write("samples/reason", reason)
        self.complete(qa_ranges=self.qa_ranges, **attrs)
