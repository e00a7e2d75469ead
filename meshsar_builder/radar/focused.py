"""The focused radar loss (issue 28 item 2): compare blurred power volumes, not raw samples.

Target: a view's echo on the loss grid (echo_clean, or the recorded noisy echo) focused by
range migration (radar.imaging.focus, the images' own focusing) onto a coarse voxel grid
in view coordinates (u, v, w), its power |I|^2 debiased by the noise's expected image
power sigma^2 P_unit, and blurred by a Gaussian. Noise and a diffuse (speckle) part add
power whose expectation is known or smooth, so this target is unbiased in expectation.

Prediction (image-domain model, differentiable, no echo): each facet of the predicted mesh
that the view sees (Embree mask on the detached mesh, as the differentiable echo) splats
its weight a_k = area_k H(s_k) / R_k^2 (R_k to the aperture centre) trilinearly into the
voxel grid, where H is the focusing's own aperture window (Hann) at s_k, the point where
the facet's specular ray (along its normal) meets the aperture plane: a locally flat
surface is imaged only where its mirror direction reaches the aperture (the k-space
support of the scan). The splat is convolved with |h|, the magnitude of the focused
point-spread function of the same scan (the focused noise-free echo of one point at the
heart centre), squared (a smooth surface adds coherently within a resolution cell: its
magnitude, not its power, is linear in area) and blurred by the same Gaussian.

Loss (focused_loss's `compare`): "cosine", 1 - cosine similarity of the two volumes per sample
and view (scale-free: the prediction carries no absolute echo scale); or "depth"
(depth_distance), the distance in mm between the two volumes' per-column depth centroids within
one range resolution of the target's peak, weighted by the target's column power: a ratio of
each column's own powers, which the model's amplitude errors leave nearly unchanged. Mean over
samples and views.

Cost: O(facets) for the splat plus 4 FFTs of the padded voxel grid per view (5 with the diffuse part), against
O(facets x antennas x frequencies) for a dense echo; the target is focused once per sample.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from meshsar_builder.radar.imaging import focus
from meshsar_builder.radar.params import (
    SPEED_OF_LIGHT_M_PER_S,
    RadarParams,
    aperture_axes,
    frequencies,
    grid_indices,
    probe_points,
    view_frame,
)


@dataclass(frozen=True)
class FocusedParams:
    """Voxel grid and blur of the focused loss (config [radar_loss] focused_*)."""

    lateral_mm: float = 2.5  # voxel size along u, v
    range_mm: float = 5.0  # voxel size along w (range resolution of the default scan is ~37 mm)
    half_extent_mm: float = 75.0  # the grid spans +-this about the heart centre on each axis (60 x 60 x 30)
    blur_mm: float = 3.0  # Gaussian sigma of the blur applied to both volumes (each axis)
    # facet weight: "specular" (the Hann window at the facet's specular aperture point) or
    # "diffuse" (lobe / R^2 toward the aperture centre only: rough surfaces glow where seen)
    reflection: str = "specular"
    depth_eps_mm: float = 1.0  # compare "depth": the Charbonnier's scale (quadratic below it, linear above)

    def __post_init__(self):
        for name in ("lateral_mm", "range_mm", "half_extent_mm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: must be > 0, got {getattr(self, name)}")
        if self.reflection not in ("specular", "diffuse"):
            raise ValueError(f"reflection: must be specular or diffuse, got {self.reflection!r}")
        if self.blur_mm < 0:
            raise ValueError(f"blur_mm: must be >= 0, got {self.blur_mm}")
        if not self.depth_eps_mm > 0:
            raise ValueError(f"depth_eps_mm: must be > 0, got {self.depth_eps_mm}")


def radar_from_index(index: dict) -> RadarParams:
    """The build's RadarParams from index.json's `radar` and `views`."""
    r = dict(index["radar"])
    keys = RadarParams.__dataclass_fields__.keys()
    kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in r.items() if k in keys}
    kwargs["views"] = tuple(v["name"] for v in index["views"])
    kwargs.setdefault("diffuse", False)  # an index from before the diffuse part had none
    return RadarParams(**kwargs)


def _axis(half: float, step: float) -> np.ndarray:
    """2 round(half / step) points `step` apart from -half, 0 at index count // 2 (even sizes: fast FFTs)."""
    count = 2 * int(round(half / step))
    return (np.arange(count) - count // 2) * step


def _padding(shape, params: FocusedParams) -> tuple[int, tuple[int, int, int]]:
    """(offset, padded shape): where the (S, H, W) grid sits along w in the zero-padded (P, H, W) grid of the FFTs.

    The PSF kernel spans S slices (S // 2 before its centre), the blur `margin` more on each
    side (6 sigma); facets are splatted within one slice of the grid. P is the least even size
    at which no circular convolution wraps a facet's contribution onto the grid or onto the
    margin the blur reads: a linear convolution's values, but for the blur's far ringing (its
    transfer is cut at the range Nyquist), 3e-6 of the peak. 2 S, which it was, did the same
    with a fifth more transform work.
    """
    s = shape[0]
    margin = math.ceil(6 * params.blur_mm / params.range_mm)
    size = max(s + s // 2 + margin + 1, 2 * s - s // 2 + margin)
    size += size % 2
    return (size - s) // 2, (size, *shape[1:])


def _gaussian_transfer(shape, spacing, sigma):
    """Real FFT transfer function (rfftn layout) of a unit-sum Gaussian of sigma mm on a grid."""
    axes = []
    for k, (n, d) in enumerate(zip(shape, spacing)):
        f = np.fft.rfftfreq(n, d) if k == len(shape) - 1 else np.fft.fftfreq(n, d)
        axes.append(np.exp(-2 * (math.pi * f * sigma) ** 2))
    return axes[0][:, None, None] * axes[1][None, :, None] * axes[2][None, None, :]


class FocusedSetup:
    """Per view: frame, loss-grid antennas and frequencies, voxel grid, PSF and blur transfer functions.

    radar: the build's RadarParams (radar_from_index); views: names of the views in use.
    The voxel grid of every view is (S, H, W) over (w, v, u); the FFT convolutions pad w to P (_padding).
    """

    def __init__(self, radar: RadarParams, views, params: FocusedParams = FocusedParams()):
        self.radar, self.views, self.params = radar, list(views), params
        ix, iy, i_f = grid_indices(radar, radar.loss_decimation)
        x_mm, y_mm = aperture_axes(radar)
        self.x_mm, self.y_mm, self.freqs = x_mm[ix], y_mm[iy], frequencies(radar)[i_f]
        self.u = _axis(params.half_extent_mm, params.lateral_mm)
        self.w = _axis(params.half_extent_mm, params.range_mm)
        self.shape = (len(self.w), len(self.u), len(self.u))  # (S, H, W): w, v, u
        self.offset, self.padded = _padding(self.shape, params)
        self.spacing = (params.range_mm, params.lateral_mm, params.lateral_mm)
        self.frames = np.stack([view_frame(v) for v in self.views])  # (V, 3, 3) rows u, v, w
        # c / 2B: the depth loss's window (the full sweep's band B, which the loss grid's frequencies span)
        sweep = frequencies(radar)
        self.range_resolution_mm = 1e3 * SPEED_OF_LIGHT_M_PER_S / (2 * len(sweep) * (sweep[1] - sweep[0]))
        self.probes = [probe_points(radar, v) for v in self.views]
        # The aperture's half extent along u and v (antenna centres): the Hann window of focus.
        self.half_aperture = ((radar.aperture[0] - 1) * radar.step_mm / 2, (radar.aperture[1] - 1) * radar.step_mm / 2)
        self.blur = _gaussian_transfer(self.padded, self.spacing, params.blur_mm)
        self.psf = self._psf()  # (S, H, W) |h| of a point at the heart centre, max 1
        # the kernel's centre voxel (the point's own) moved to index 0: a convolution that shifts nothing
        centre = (self.offset + self.shape[0] // 2, self.shape[1] // 2, self.shape[2] // 2)
        self.psf_transfer = np.fft.rfftn(np.roll(self._centred(self.psf), [-c for c in centre], axis=(0, 1, 2)))
        # |h|^2: how the diffuse part's scatterers add, incoherently, in expectation
        self.psf_power_transfer = np.fft.rfftn(np.roll(self._centred(self.psf**2), [-c for c in centre],
                                                       axis=(0, 1, 2)))
        self.unit_noise_power = self._unit_noise_power()
        self._torch = {}

    # ------------------------------------------------------------ numpy: targets

    def focus_view(self, echo: np.ndarray) -> np.ndarray:
        """Complex image (S, H, W) of one view's loss-grid echo (Lx, Ly, Lf) on the voxel grid."""
        d = self.radar.z0_mm - self.w  # distance from the aperture plane, descending
        return focus(np.asarray(echo), self.freqs, self.x_mm, self.y_mm, self.u, self.u, d, "hann")

    def _centred(self, volume: np.ndarray) -> np.ndarray:
        """volume (S, H, W) zero-padded along w to (P, H, W) at self.offset."""
        out = np.zeros(self.padded, dtype=np.float64)
        out[self.offset: self.offset + self.shape[0]] = volume
        return out

    def _psf(self) -> np.ndarray:
        from meshsar_builder.radar.echo import point_echo

        frame = self.frames[0]
        nx, ny = len(self.x_mm), len(self.y_mm)
        positions = (self.x_mm[:, None, None] * frame[0] + self.y_mm[None, :, None] * frame[1]
                     + self.radar.z0_mm * frame[2]).reshape(-1, 3)
        echo = point_echo(np.zeros((1, 3)), frame[2][None], np.ones(1), positions, self.freqs, self.radar)
        magnitude = np.abs(self.focus_view(echo.reshape(nx, ny, -1))).astype(np.float64)
        return magnitude / magnitude.max()

    def _unit_noise_power(self) -> float:
        """Mean |image|^2 of unit-power white complex noise on the loss grid (sigma^2 times this is the bias)."""
        rng = np.random.default_rng(0)
        shape = (len(self.x_mm), len(self.y_mm), len(self.freqs))
        total = 0.0
        for _ in range(2):
            noise = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / math.sqrt(2)
            total += float(np.mean(np.abs(self.focus_view(noise.astype(np.complex64))) ** 2))
        return total / 2

    def blurred(self, volume: np.ndarray) -> np.ndarray:
        """Gaussian blur of a (S, H, W) volume (zero-padded along w)."""
        out = np.fft.irfftn(np.fft.rfftn(self._centred(volume)) * self.blur, s=self.padded, axes=(0, 1, 2))
        return out[self.offset: self.offset + self.shape[0]]

    def target(self, echo: np.ndarray, sigma: float = 0.0) -> np.ndarray:
        """Debiased, blurred power (V, S, H, W) float32 of a sample's loss-grid echo (V, Lx, Ly, Lf).

        sigma: the noise's per-sample standard deviation (noise_sigma; 0 for echo_clean), a
        scalar or one per view: sigma^2 times the unit noise's image power is subtracted.
        """
        sigmas = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (len(echo),))
        out = []
        for view_echo, s in zip(echo, sigmas):
            power = np.abs(self.focus_view(view_echo)).astype(np.float64) ** 2 - s * s * self.unit_noise_power
            out.append(self.blurred(power))
        return np.stack(out).astype(np.float32)

    # ------------------------------------------------------------ torch: prediction

    def _tensors(self, device, dtype):
        key = (str(device), dtype)
        if key not in self._torch:
            self._torch[key] = {
                "frames": torch.as_tensor(self.frames, dtype=dtype, device=device),
                "psf": torch.as_tensor(self.psf_transfer, dtype=torch.complex64 if dtype == torch.float32
                                       else torch.complex128, device=device),
                "psf_power_blur": torch.as_tensor(self.psf_power_transfer * self.blur,
                                                  dtype=torch.complex64 if dtype == torch.float32 else torch.complex128,
                                                  device=device),
                "blur": torch.as_tensor(self.blur, dtype=dtype, device=device),
            }
        return self._torch[key]

    def weights(self, centroids, normals, areas, view: int):
        """Facet weights a_k (..., F) of one view: area / R^2 x the Hann window at the specular point.

        (reflection "diffuse": x the lobe toward the aperture centre instead of the window.)
        """
        t = self._tensors(centroids.device, centroids.dtype)
        frame = t["frames"][view]
        c = centroids @ frame.T  # (..., F, 3) view coordinates u, v, w
        n = normals @ frame.T
        z0 = self.radar.z0_mm
        nw = n[..., 2].clamp_min(1e-3)
        reach = (z0 - c[..., 2]) / nw  # distance along the normal to the aperture plane
        su = c[..., 0] + reach * n[..., 0]
        sv = c[..., 1] + reach * n[..., 1]
        hu, hv = self.half_aperture
        window = (torch.cos((math.pi / 2) * (su / hu).clamp(-1, 1)) ** 2
                  * torch.cos((math.pi / 2) * (sv / hv).clamp(-1, 1)) ** 2)
        window = torch.where(n[..., 2] > 0, window, torch.zeros_like(window))
        to_centre = torch.stack([-c[..., 0], -c[..., 1], z0 - c[..., 2]], dim=-1)
        r2 = (to_centre * to_centre).sum(-1)
        if self.params.reflection == "diffuse":
            cos = ((to_centre * n).sum(-1) / r2.sqrt()).clamp_min(0)
            radar = self.radar
            window = cos if radar.reflectivity == "po" else (1 - radar.kappa) * cos ** radar.p + radar.kappa * cos
        # specular: the antenna that sees the facet's mirror reflection sees it at normal incidence (lobe 1)
        return areas * window * (z0 * z0) / r2, c

    def diffuse_weights(self, centroids, normals, areas, visibility, view: int):
        """Expected diffuse power per facet (..., F), in the units of the specular weights squared.

        The production diffuse part (radar.diffuse): scatterers of mean power beta per mm^2,
        amplitude times the facet's visibility V, Lambert's cos toward the aperture centre,
        1 / R^2: beta area V^2 cos^2 (z0 / R)^4, the specular weights' z0^2 / R^2 squared.
        """
        from meshsar_builder.radar.diffuse import mean_power_per_area

        frame = self._tensors(centroids.device, centroids.dtype)["frames"][view]
        c = centroids @ frame.T
        n = normals @ frame.T
        z0 = self.radar.z0_mm
        to_centre = torch.stack([-c[..., 0], -c[..., 1], z0 - c[..., 2]], dim=-1)
        r2 = (to_centre * to_centre).sum(-1)
        cos = ((to_centre * n).sum(-1) / r2.sqrt()).clamp_min(0)
        return mean_power_per_area(self.radar) * areas * visibility**2 * cos**2 * (z0 * z0 / r2) ** 2

    def splat(self, coords: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """Trilinear splat of weights (B, C, F) at view coordinates (B, F, 3) into (B, C, P, H, W), the grid at
        self.offset along w.

        C channels share the facets' positions (the specular and diffuse parts); the eight
        corners of every facet and channel go in one scatter_add. Along w only the grid and
        one slice either side take weight (_padding: beyond, the convolutions would wrap).
        """
        batch, channels = weights.shape[:2]
        sizes = self.padded
        # fractional voxel indices along (w, v, u); the padded w axis starts self.offset slices earlier
        position = torch.stack([(coords[..., 2] - self.w[0]) / self.params.range_mm + self.offset,
                                (coords[..., 1] - self.u[0]) / self.params.lateral_mm,
                                (coords[..., 0] - self.u[0]) / self.params.lateral_mm])  # (3, B, F)
        base = position.detach().floor()
        frac = position - base
        base = base.long()
        corner = torch.tensor([[dw, dv, du] for dw in (0, 1) for dv in (0, 1) for du in (0, 1)],
                              device=base.device).T[:, :, None, None]  # (3, 8, 1, 1)
        index = base[:, None] + corner  # (3, 8, B, F)
        share = torch.where(corner.bool(), frac[:, None], 1 - frac[:, None]).prod(0)  # (8, B, F) trilinear weights
        low = torch.tensor([self.offset - 1, 0, 0], device=base.device)[:, None, None, None]
        limit = torch.tensor([self.offset + self.shape[0] + 1, *sizes[1:]], device=base.device)[:, None, None, None]
        inside = ((index >= low) & (index < limit)).all(0)  # (8, B, F)
        index = torch.minimum(index.clamp_min(0), limit - 1)
        flat = (index[0] * sizes[1] + index[1]) * sizes[2] + index[2]  # (8, B, F)
        values = torch.where(inside, share, torch.zeros_like(share))[:, :, None] * weights  # (8, B, C, F)
        flat = flat[:, :, None].expand_as(values)
        offset = torch.arange(channels, device=base.device)[:, None] * (sizes[0] * sizes[1] * sizes[2])  # (C, 1)
        out = torch.zeros(batch, channels * sizes[0] * sizes[1] * sizes[2], dtype=weights.dtype,
                          device=weights.device)
        # in place: the out-of-place scatter_add copies the zeros first (a tenth of the term's time)
        out.scatter_add_(1, (flat + offset).permute(1, 2, 0, 3).reshape(batch, -1),
                         values.permute(1, 2, 0, 3).reshape(batch, -1))
        return out.reshape(batch, channels, *sizes)

    def predicted(self, verts: torch.Tensor, faces: torch.Tensor, view: int, mask: torch.Tensor | None = None,
                  parts: tuple[str, ...] = ("specular", "diffuse")):
        """Predicted blurred power (B, S, H, W) of one view for verts (B, n, 3) mm, faces (m, 3) long.

        parts: the specular part, and the diffuse part's expected power where the build has
        one (radar.diffuse); the tests check each against the production echo on its own.
        """
        from meshsar_builder.radar.differentiable import facet_geometry_torch, occlusion_mask

        t = self._tensors(verts.device, verts.dtype)
        if mask is None:
            mask = occlusion_mask(verts, faces, self.probes[view])  # (B, m)
        seen = (mask > 0).any(0)
        faces, mask = faces[seen], mask[:, seen]
        centroids, normals, areas = facet_geometry_torch(verts, faces)
        weights, coords = self.weights(centroids, normals, areas * mask, view)
        channels = [weights * ("specular" in parts)]
        diffuse = self.radar.diffuse and "diffuse" in parts  # the diffuse part's expected power beside the specular
        if diffuse:
            channels.append(self.diffuse_weights(centroids, normals, areas, mask, view))
        # unbind, not indexing: each index's backward fills a zeroed (B, C, P, H, W) of its own
        grids = self.splat(coords, torch.stack(channels, dim=1)).unbind(1)  # C x (B, P, H, W)
        magnitude = fixed_convolution(grids[:1], (t["psf"],), self.padded)
        volumes, transfers = (magnitude * magnitude,), (t["blur"],)
        if diffuse:  # |h|^2 (scatterers add incoherently), then the blur
            volumes, transfers = (*volumes, grids[1]), (*transfers, t["psf_power_blur"])
        power = fixed_convolution(volumes, transfers, self.padded)
        return power[:, self.offset: self.offset + self.shape[0]]


class _FixedConvolution(torch.autograd.Function):
    """fixed_convolution with its adjoint as the backward pass (see there)."""

    @staticmethod
    def forward(ctx, shape, transfers, *volumes):
        ctx.shape, ctx.transfers = shape, transfers
        spectrum = sum(torch.fft.rfftn(v, dim=(1, 2, 3)) * h for v, h in zip(volumes, transfers))
        return torch.fft.irfftn(spectrum, s=shape, dim=(1, 2, 3))

    @staticmethod
    def backward(ctx, grad):
        spectrum = torch.fft.rfftn(grad, dim=(1, 2, 3))
        return (None, None, *(torch.fft.irfftn(spectrum * h.conj(), s=ctx.shape, dim=(1, 2, 3)) if wanted else None
                              for h, wanted in zip(ctx.transfers, ctx.needs_input_grad[2:])))


def fixed_convolution(volumes, transfers, shape) -> torch.Tensor:
    """sum_i h_i (*) x_i, (B, *shape): circular convolutions of real volumes x_i (B, *shape), fixed real kernels h_i.

    transfers : each kernel's rfftn over the three volume axes, complex (shape[0], shape[1],
    shape[2] // 2 + 1) or broadcastable to it. The gradient is the adjoint, correlation with
    each kernel (conj(h_i) in frequency), one rfftn and one irfftn per input: torch's own
    backward of rfftn goes through a full complex FFT and copies, twice the cost (the focused
    loss's FFTs were a third of its forward and backward on the CPU).
    """
    return _FixedConvolution.apply(tuple(shape), tuple(transfers), *volumes)


def focused_loss(verts: torch.Tensor, faces: torch.Tensor, targets: torch.Tensor, setup: FocusedSetup,
                 masks: list[torch.Tensor] | None = None, compare: str = "cosine") -> torch.Tensor:
    """Mean over samples and views of a distance between predicted and target blurred power volumes.

    verts (B, n, 3) mm; faces (m, 3) long; targets (B, V, S, H, W) from setup.target; masks:
    occlusion_masks of verts for setup.probes (V x (B, m)), or None to trace them here.
    compare: "cosine" (1 - cos of the volumes) or "depth" (depth_distance: their depth maps).
    """
    from meshsar_builder.radar.differentiable import occlusion_masks

    faces = torch.as_tensor(faces, dtype=torch.long, device=verts.device)
    if masks is None:
        masks = occlusion_masks(verts, faces, setup.probes[: targets.shape[1]])  # V x (B, m), one scene a mesh
    distance = {"cosine": cosine_distance, "depth": functools.partial(depth_distance, setup=setup)}[compare]
    terms = [distance(setup.predicted(verts, faces, v, masks[v]), targets[:, v]) for v in range(targets.shape[1])]
    return torch.stack(terms).mean()


def depth_window(target: torch.Tensor, slices: float) -> torch.Tensor:
    """(B, S, H, W) a Hann taper along w about each column's peak: 1 at the peak, 0 from `slices` away.

    target (B, S, H, W) power volumes. The range focus spreads a surface over the range
    resolution; beyond it a column holds other surfaces' sidelobes, which bias its centroid.
    """
    index = torch.arange(target.shape[1], device=target.device)[None, :, None, None]  # (1, S, 1, 1)
    offset = (index - target.argmax(1, keepdim=True)).abs().to(target.dtype)  # (B, S, H, W)
    return torch.cos((math.pi / 2) * (offset / slices).clamp(max=1)) ** 2


def column_depth(volume: torch.Tensor, window: torch.Tensor, w_mm: torch.Tensor):
    """Depth centroid (B, H, W) mm along w of each column's windowed power, and that power (B, H, W).

    volume, window (B, S, H, W); w_mm (S,) the slices' w. Negative power (the debiased target's
    noise) counts as none. Columns without power get depth 0 (their weight is 0).
    """
    power = volume.clamp_min(0) * window  # (B, S, H, W)
    total = power.sum(1)  # (B, H, W)
    depth = (power * w_mm[:, None, None]).sum(1) / total.clamp_min(torch.finfo(total.dtype).tiny)  # (B, H, W)
    return depth, total


def depth_distance(predicted: torch.Tensor, target: torch.Tensor, setup: FocusedSetup) -> torch.Tensor:
    """(B,) the target-power-weighted Charbonnier distance (mm) between two volumes' depth maps (one view's).

    predicted, target (B, S, H, W). Each column's depth is the centroid of its power within one
    range resolution of the target's peak (depth_window; the same window on both sides), so a
    surface's depth is compared where the radar sees it, and the prediction's amplitudes, which
    the image-domain model gets wrong by tens of per cent, cancel in each column's ratio.
    Weights: the target's column powers, summing to 1 per sample; columns where the prediction
    has no power are left out. rho(d) = sqrt(d^2 + eps^2) - eps, eps = setup.params.depth_eps_mm.
    """
    target = target.to(predicted)
    window = depth_window(target, setup.range_resolution_mm / setup.params.range_mm)  # (B, S, H, W)
    w_mm = torch.as_tensor(setup.w, dtype=predicted.dtype, device=predicted.device)
    z_target, weight = column_depth(target, window, w_mm)  # (B, H, W) each
    z_predicted, power = column_depth(predicted, window, w_mm)  # (B, H, W) each
    seen = power.detach() > 1e-6 * power.detach().flatten(1).amax(1)[:, None, None]  # (B, H, W)
    weight = torch.where(seen, weight, torch.zeros_like(weight))
    eps = setup.params.depth_eps_mm
    rho = torch.sqrt((z_predicted - z_target) ** 2 + eps * eps) - eps  # (B, H, W)
    return (weight * rho).flatten(1).sum(1) / weight.flatten(1).sum(1).clamp_min(1e-30)  # (B,)


def cosine_distance(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) 1 - cos(predicted, target) of each sample's volume: predicted, target (B, ...) (one view's volumes)."""
    pred = predicted.flatten(1)  # (B, N)
    tgt = target.to(pred).flatten(1)  # (B, N)
    return 1 - (pred * tgt).sum(1) / (pred.norm(dim=1) * tgt.norm(dim=1)).clamp_min(1e-30)  # (B,)
