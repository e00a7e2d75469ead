"""Radar physics: parameters and views, visibility, the FMCW echo, SAR imaging, the differentiable echo.

Imports `pipeline` only; torch only in `differentiable` and `gpu`. Modules: `params`
(RadarParams, view frames, aperture, echo grid), `visibility` (facet geometry, Embree),
`echo` (direct reference and fast production sums, noise), `imaging` (range migration,
view images), `render` (one sample, every view), `differentiable` (torch echo for the
radar loss), `gpu` (a view's echo and imaging on a torch device, for device = "cuda";
imported only then).
"""
