"""The root configuration: one section per stage."""

from __future__ import annotations

from pydantic import Field, model_validator

from gtgen.config.base import LIDAR_REFERENCE, RANGES, GridsConfig, TopicsConfig, _Model
from gtgen.config.stages import DemConfig, ExtractConfig, FuseConfig, MappingConfig, ReportConfig, ShardsConfig, TrainConfig
from gtgen.config.synth import SynthConfig

MAX_SUB_CELLS = 8  # sub-cells a side of a map cell judged by its cover (mapping.cover_cell_m): 64 floats a cell at most


class GtgenConfig(_Model):
    """Root configuration; every stage reads its own part."""

    grids: GridsConfig = Field(default_factory=GridsConfig)
    topics: TopicsConfig = Field(default_factory=TopicsConfig)
    synth: SynthConfig = Field(default_factory=SynthConfig)
    extract: ExtractConfig = Field(default_factory=ExtractConfig)
    fuse: FuseConfig = Field(default_factory=FuseConfig)
    dem: DemConfig = Field(default_factory=DemConfig)
    shards: ShardsConfig = Field(default_factory=ShardsConfig)
    report: ReportConfig = Field(default_factory=ReportConfig)
    train: TrainConfig = Field(default_factory=TrainConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)

    @model_validator(mode="after")
    def _reference_is_a_sensor(self) -> GtgenConfig:
        ref = self.extract.reference
        if ref is not None and ref != LIDAR_REFERENCE and ref not in self.topics.cameras:
            raise ValueError(f"extract.reference = {ref!r} names no configured sensor; expected one of "
                             f"{[*self.topics.cameras, LIDAR_REFERENCE]} (a camera of topics.cameras, or the lidar)")
        if ref == LIDAR_REFERENCE and not self.topics.lidar:
            raise ValueError("extract.reference = 'lidar', but topics.lidar lists no lidar topic")
        # a cell's sub-cell tops take sub^2 floats a cell of the rolling map: judged on the coarsest grid
        r = max(RANGES, key=lambda r: self.mapping.sub_cells(self.grids.get(r).resolution_m))
        res = self.grids.get(r).resolution_m
        sub = self.mapping.sub_cells(res)
        if sub > MAX_SUB_CELLS:
            raise ValueError(f"mapping.cover_cell_m = {self.mapping.cover_cell_m} splits the {r} grid's {res} m cells into {sub} x {sub} "
                             f"sub-cells; expected at most {MAX_SUB_CELLS} x {MAX_SUB_CELLS} (cover_cell_m >= {res / (MAX_SUB_CELLS + 0.5):.3g} m), "
                             "or null")
        return self

    @property
    def reference(self) -> str:
        """The sensor sample times snap to: ``extract.reference``, else the first camera, else 'lidar'."""
        if self.extract.reference is not None:
            return self.extract.reference
        return next(iter(self.topics.cameras), LIDAR_REFERENCE)
