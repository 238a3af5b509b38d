"""The dataset: per-sample labels, baselines and paired inputs assembled from a drive's
fused labels and DEM placement (``run_dem_align``), written shard by shard, and merged
across drives (``DatasetMerger``)."""
