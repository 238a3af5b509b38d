"""Hindsight fusion: X-Racer maps of a window fused into each sample's target grid."""
