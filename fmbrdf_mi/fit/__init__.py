"""Inverse rendering: estimate FMBRDF parameters from polarimetric images (paper section 5).

    result = fit(obs)                     # obs: an Observation; result.params: eta, alpha, beta, kappa, k_s, r_k
    joint = fit([obs_1, obs_2, obs_3])    # several images of one object, one material (= fit_joint)

Layers, each importing only from those before it (``tests/test_layers.py``): ``errors``, ``inputs``,
``evaluate``, ``objectives``, ``problem``, ``solve``, ``uncertainty``, ``result``, ``api``, ``outputs``, ``cli``."""
from fmbrdf_mi.fit.api.colour import fit_colour
from fmbrdf_mi.fit.api.find_materials import FoundMaterials, MaterialsNotSeparated, find_materials
from fmbrdf_mi.fit.api.fitting import FitOptions, fit, fit_joint, usable_pixels
from fmbrdf_mi.fit.api.normal_joint import refine_joint
from fmbrdf_mi.fit.errors import InputError
from fmbrdf_mi.fit.evaluate.predict import predict_image
from fmbrdf_mi.fit.inputs.manifest import ImageSpec, read_manifest
from fmbrdf_mi.fit.inputs.observations import Observation
from fmbrdf_mi.fit.outputs.joint import fit_images
from fmbrdf_mi.fit.outputs.single import fit_files
from fmbrdf_mi.fit.result import FitResult

__all__ = ["fit", "fit_joint", "fit_colour", "refine_joint", "fit_files", "fit_images",
           "FitOptions", "FitResult", "predict_image", "usable_pixels", "Observation", "ImageSpec",
           "read_manifest", "InputError", "find_materials", "FoundMaterials", "MaterialsNotSeparated"]
