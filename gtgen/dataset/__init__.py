"""The dataset: per-sample labels, baselines and paired inputs assembled from a drive's
fused labels and DEM placement (``dem_align.run_dem_align``), and merged across drives
(``merge.DatasetMerger``); the store itself is ``gtgen.storage.dataset``."""
