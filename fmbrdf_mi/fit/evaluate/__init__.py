"""The reflectance models and their evaluation at a fit's pixels (per pixel or by rendering); predictions."""
