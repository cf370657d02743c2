"""Fitting FMBRDF to measured isotropic BRDFs (the MERL database format): ``fmbrdf-mi fit-brdf``.

* :mod:`.merl`: the MERL binary format and its half/difference-angle grid;
* :mod:`.values`: unpolarised FMBRDF values (M00) for many direction pairs, through the plugin;
* :mod:`.fitting`: sample selection, start grid and log-space least squares;
* :mod:`.plots`, :mod:`.command`: outputs and the subcommand;
* Mueller-matrix BRDF tables (``fit-brdf TABLE.csv|.npz``): :mod:`.mueller` (the SCATMECH/NIST layout and
  the plain table, in the plugin's Stokes frames), :mod:`.mueller_values` (the polarised evaluator of
  fmbrdf, pplastic and a Lambertian), :mod:`.mueller_fit` (the weighted fit, intervals, held-out errors),
  :mod:`.mueller_plots` and :mod:`.mueller_command`.
"""
