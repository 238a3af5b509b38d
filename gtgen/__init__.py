"""gtgen: pseudo ground truth for BEV elevation and traversability learning.

Data flow: ``bag/`` (extract) -> ``fuse/`` (hindsight fusion) -> ``dem/`` (DEM
alignment and inpainting) -> ``shards/`` (Zarr v3 dataset) -> ``train/``.
"""

from gtgen.errors import GtgenError

__version__ = "0.1.0"

__all__ = ["GtgenError", "__version__"]
