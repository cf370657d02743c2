#!/usr/bin/env bash
# Regenerate the README's preview images in docs/images/ with the fmbrdf-mi CLI
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
