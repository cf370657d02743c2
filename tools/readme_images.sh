#!/usr/bin/env bash
# Regenerate the preview images in docs/images/ (README and documentation) with the fmbrdf-mi CLI
# (default variant llvm_ad_spectral_polarized, default scene and scenes/spheres.xml).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
$PY -m fmbrdf_mi render "$tmp/sphere.exr" --angles --mosaic -q
$PY -m fmbrdf_mi render "$tmp/mod/sphere.exr" --aolp-dolp -q
$PY -m fmbrdf_mi render -s scenes/spheres.xml "$tmp/spheres.exr" -q
mkdir -p docs/images
cp "$tmp"/sphere_{intensity,dolp,aolp,angles,mosaic}.png "$tmp"/spheres_{intensity,dolp,aolp}.png docs/images/
cp "$tmp/mod/sphere_aolp.png" docs/images/sphere_aolp_dolp.png
# the fitting example of docs/howto/fit.md (about a minute)
$PY -m fmbrdf_mi render --variant llvm_ad_mono_polarized -D alpha=0.15 -D light_dir=-0.5,0.5,1 "$tmp/a.exr" -q
$PY -m fmbrdf_mi render --variant llvm_ad_mono_polarized -D alpha=0.15 -D light_dir=0.7,-0.2,0.6 "$tmp/b.exr" -q
$PY -m fmbrdf_mi fit "$tmp/a.exr" --relight "$tmp/b.exr" --baselines -o "$tmp/fit_a" -q
cp "$tmp/fit_a/profiles.png" docs/images/fit_profiles.png
cp "$tmp/fit_a/images.png" docs/images/fit_images.png
