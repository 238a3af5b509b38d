"""``gtgen synth``: a seeded synthetic X-Racer drive with known truth.

Layout of OUT (documented in data_schema.md):
``drive.mcap`` (bare ROS 2 MCAP), ``drive.bag`` (ROS 1), ``dem/*.tif`` (1 m DEM tiles),
``truth/`` (what rebuilds the world), ``gtgen-config.yaml`` (the resolved config).
"""

from gtgen.synth.run import SynthResult, run_synth

__all__ = ["SynthResult", "run_synth"]
