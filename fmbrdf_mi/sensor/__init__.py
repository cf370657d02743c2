"""The polarisation camera, modelled once for rendering and fitting.

``mosaic``   polariser angles, raw mono and colour mosaics, demosaicking to Stokes
``camera``   :class:`~fmbrdf_mi.sensor.camera.CameraModel`: exposure, shot and read noise, ADC; captures, sidecars
``noise``    the variance of a sample and of a demosaicked Stokes image; pixel footprints
``samples``  the raw samples of each cell of the fit's grid (mono 2x2, colour 4x4) and which are clipped
``rice``     the mean DoLP a noisy camera measures (the Rice mean)
"""
