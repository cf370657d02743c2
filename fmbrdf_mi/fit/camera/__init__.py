"""The camera's measurement: noise model, raw samples per super-pixel (mono 2x2, colour 4x4 periods), demosaicking,
footprints, the DoLP's noise bias."""
