"""Validated configuration: one pydantic model per stage, nested in :class:`GtgenConfig`.

No file at all gives working defaults; a YAML file is a partial override of them
(``--config FILE``). ``configs/default.yaml`` lists every key with its unit and a
test keeps it equal to these defaults.

The package follows the data flow: ``base`` (what every stage shares: ranges, grids,
topics), ``synth`` (the simulated drive), ``stages`` (extract, fuse, dem-align, report,
shards, the trainer, the mapping of raw lidar), ``root`` (:class:`GtgenConfig`, one section
per stage) and ``files`` (YAML layers merged and validated, one-line errors, the defaults
written out). Import from ``gtgen.config``.
"""

from gtgen.config.base import (
    CAMERAS,
    LIDAR_REFERENCE,
    LIDAR_TOPICS,
    LIDARS,
    MAX_CAMERAS,
    MAX_SPAN_S,
    RANGES,
    CameraTopics,
    GridsConfig,
    GridSpec,
    LayersConfig,
    TopicsConfig,
)
from gtgen.config.files import build_config, check_value, configs_dir, default_yaml, load_config, read_yaml, save_config, stored_config
from gtgen.config.root import GtgenConfig
from gtgen.config.stages import (
    DemConfig,
    ExtractConfig,
    FuseConfig,
    MappingConfig,
    PrecisionConfig,
    ReportConfig,
    ShardsConfig,
    TrainConfig,
)
from gtgen.config.synth import EASY_WORLD, SynthConfig

__all__ = [
    "CAMERAS", "EASY_WORLD", "LIDARS", "LIDAR_REFERENCE", "LIDAR_TOPICS", "MAX_CAMERAS", "MAX_SPAN_S", "RANGES",
    "CameraTopics", "DemConfig", "ExtractConfig", "FuseConfig", "GridSpec", "GridsConfig", "GtgenConfig", "LayersConfig",
    "MappingConfig", "PrecisionConfig", "ReportConfig", "ShardsConfig", "SynthConfig", "TopicsConfig", "TrainConfig",
    "build_config", "check_value", "configs_dir", "default_yaml", "load_config", "read_yaml", "save_config", "stored_config",
]
