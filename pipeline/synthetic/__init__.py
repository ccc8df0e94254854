"""Synthetic captures with ground truth (paper sec. 6, Table 1).

* :mod:`.phantoms` - refractivity over time from temperature (Gladstone-Dale): Gaussian
  blob, three tea-light plumes, a buoyant plume from :mod:`.smoke` (Boussinesq simulation).
* :mod:`.tracer` - curved rays through ``n`` by RK4 on the ray equation (eq. 1-2).
* :mod:`.rig` - calibrated pinhole cameras on a half or full ring, one background each.
* :mod:`.background` - Wavelet Noise (Cook and DeRose 2005), evaluated procedurally.
* :mod:`.render` - frames through the flow: rolling shutter, supersampling, noise, flash.

Pure kernels: no file I/O, no dask, no zarr (files: ``storage.synthetic_io``; glue:
``workers.synth``).
"""
