"""Grid maps from raw lidar: what a range's map is where no autonomy stack publishes one.

``cells`` holds the points of the recent sweeps per world-fixed cell (a ring buffer that
rolls with the vehicle), ``layers`` turns a window of cells into the stack's layers
(ground elevation, risk from geometry, confidence, and the top surface), ``mapper`` feeds
sweeps in time order and makes the maps.
"""
