"""Exports of a dataset to the tools people already look with: GeoTIFF mosaics for GIS
(``gtgen.export.geotiff``) and one MCAP recording for Foxglove (``gtgen.export.mcap``)."""

from gtgen.export.geotiff import export_geotiff
from gtgen.export.mcap import export_mcap

__all__ = ["export_geotiff", "export_mcap"]
