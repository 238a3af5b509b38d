"""M&M-lite: a lightweight RoadRunner M&M trainer and the paper's evaluation tables."""
