"""DEM placement (GNSS fit + ICP), fitness rejection, and inpainting of unobserved cells."""
