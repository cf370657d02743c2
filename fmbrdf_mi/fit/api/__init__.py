"""The fits as functions: one image, several images (joint, free powers), colour mosaics, normal refinement."""
