"""Fitting FMBRDF to measured isotropic BRDFs (the MERL database format): ``fmbrdf-mi fit-brdf``.

* :mod:`.merl`: the MERL binary format and its half/difference-angle grid;
* :mod:`.values`: unpolarised FMBRDF values (M00) for many direction pairs, through the plugin;
* :mod:`.fitting`: sample selection, start grid and log-space least squares;
* :mod:`.plots`, :mod:`.command`: outputs and the subcommand.
"""
