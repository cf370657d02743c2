"""What a fit is given: :class:`~fmbrdf_mi.fit.inputs.observations.Observation` and the loaders of its inputs."""
