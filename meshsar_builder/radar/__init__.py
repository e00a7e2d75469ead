"""Radar physics: parameters and views, visibility, the FMCW echo, SAR imaging, the differentiable echo.

Imports `pipeline` only; torch only in `differentiable`, `focused` and `gpu`. Modules: `params`
(RadarParams, view frames, aperture, echo grid), `visibility` (facet geometry, Embree),
`echo` (direct reference and fast production sums), `noise` (the recorded noise from a
seed per view, for the build and for readers), `imaging` (range migration, view images),
`render` (one sample, every view), `ghosts` (the ghost level of a decimated echo grid,
which chose the loss grid), `differentiable` (torch echo for the radar loss), `focused`
(the focused radar loss: an image-domain model of a mesh and its focused target), `gpu`
(a view's echo and imaging on a torch device, for device = "cuda"; imported only then).
"""
