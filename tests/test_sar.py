"""SAR imaging: a point scatterer images where the DESIGN projection puts it, with the theoretical resolution."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import meshsar_builder.radar.echo as RE
import meshsar_builder.radar.params as RP
from meshsar_builder.radar import imaging as S

RADAR = RP.RadarParams()
IMAGES = S.ImageParams()
PIXEL_MM = IMAGES.fov_mm / IMAGES.size
# Components at 8.5, -18.5 and 13.5 pixels plus a little: in every preset view the
# point sits well inside one pixel (0.5 +- 0.2 of it), whatever the signs.
POINT = np.array([8.5 * PIXEL_MM + 0.2, -18.5 * PIXEL_MM - 0.15, 13.5 * PIXEL_MM + 0.25])


def point_echo(view, point=POINT, radar=RADAR):
    """Echo (Nx, Ny, N) of one scatterer facing the radar."""
    frame = RP.view_frame(view)
    signal = RE.point_echo(point[None], frame[2][None], np.ones(1), RP.aperture_positions(radar, view),
                    RP.frequencies(radar), radar)
    return signal.reshape(*radar.aperture, radar.n_samples)


def projected_pixel(point, view, images=IMAGES):
    """(row, col) containing the grid_sample coordinates x = 2u/fov, y = -2v/fov (align_corners=False)."""
    u, v, _ = RP.view_frame(view) @ point
    x, y = 2 * u / images.fov_mm, -2 * v / images.fov_mm
    return int(np.floor((y + 1) / 2 * images.size)), int(np.floor((x + 1) / 2 * images.size))


def test_pixel_centres_follow_the_design_grid():
    u, v = S.pixel_centres(4, 8.0)
    np.testing.assert_allclose(u, [-3, -1, 1, 3])
    np.testing.assert_allclose(v, [3, 1, -1, -3])


def test_grid_sample_reads_the_pixel_of_a_projected_point():
    torch = pytest.importorskip("torch")
    image = torch.zeros(1, 1, IMAGES.size, IMAGES.size, dtype=torch.float64)
    row, col = projected_pixel(POINT, "anterior")
    image[0, 0, row, col] = 1.0
    u, v = S.pixel_centres(IMAGES.size, IMAGES.fov_mm)
    grid = torch.tensor([[[[2 * u[col] / IMAGES.fov_mm, -2 * v[row] / IMAGES.fov_mm]]]], dtype=torch.float64)
    sampled = torch.nn.functional.grid_sample(image, grid, align_corners=False)
    assert sampled.item() == pytest.approx(1.0)


@pytest.mark.parametrize("view", list(RP.VIEW_FRAMES))
def test_point_images_at_its_projection_and_range(view):
    x_mm, y_mm = RP.aperture_axes(RADAR)
    channels = S.view_images(point_echo(view), RP.frequencies(RADAR), x_mm, y_mm, RADAR.z0_mm, IMAGES)
    intensity, depth = channels
    row, col = np.unravel_index(np.argmax(intensity), intensity.shape)
    assert (row, col) == projected_pixel(POINT, view)
    assert intensity[row, col] == 1.0
    # Depth is w / (fov/2). Range migration with an aperture this short puts the
    # peak ~1 mm towards the radar (backprojection puts it exactly): 3 % of c/2B.
    w = RP.view_frame(view)[2] @ POINT
    assert depth[row, col] * IMAGES.fov_mm / 2 == pytest.approx(w, abs=2.0)
    assert (depth[intensity < S.DEPTH_INTENSITY_FLOOR] == 0).all()


def minus_3db_width(coords, magnitude):
    """Width (same unit as coords) where magnitude >= max / sqrt(2), crossings linearly interpolated."""
    level = magnitude.max() / np.sqrt(2)
    above = np.nonzero(magnitude >= level)[0]
    lo, hi = above[0], above[-1]
    left = np.interp(level, [magnitude[lo - 1], magnitude[lo]], [coords[lo - 1], coords[lo]])
    right = np.interp(level, [magnitude[hi + 1], magnitude[hi]], [coords[hi + 1], coords[hi]])
    return right - left


def point_cuts(radar, view="anterior"):
    """-3 dB widths (mm) of a point's image across range (along u) and along range (w), window "none"."""
    u0, v0, w0 = RP.view_frame(view) @ POINT
    d0 = radar.z0_mm - w0
    f = RP.frequencies(radar)
    x_mm, y_mm = RP.aperture_axes(radar)
    signal = point_echo(view, radar=radar)
    fine = np.linspace(-1, 1, 401)
    across = S.focus(signal, f, x_mm, y_mm, u0 + 12 * fine, np.array([v0]), np.array([d0]), "none")[0, 0]
    along = S.focus(signal, f, x_mm, y_mm, np.array([u0]), np.array([v0]), d0 + 60 * fine, "none")[:, 0, 0]
    return minus_3db_width(12 * fine, np.abs(across)), minus_3db_width(60 * fine, np.abs(along)), d0


def test_point_resolution_matches_theory():
    f = RP.frequencies(RADAR)
    wavelength = S.SPEED_OF_LIGHT_MM_PER_S / f.mean()
    across, along, d0 = point_cuts(RADAR)
    assert across == pytest.approx(wavelength * d0 / (2 * RADAR.aperture[0] * RADAR.step_mm), rel=0.25)
    assert S.range_resolution_mm(f) == pytest.approx(37.47, abs=0.01)
    # c/2B is the range width while the aperture's depth of focus is much longer:
    # a 32 mm aperture at 323 mm spans +-4 degrees.
    narrow = RP.RadarParams(aperture=(16, 16))
    assert point_cuts(narrow)[1] == pytest.approx(S.range_resolution_mm(f), rel=0.25)
    # The default 160 mm aperture spans +-19 degrees (corners): its kz support
    # reaches 2 k cos(19 deg), so the 3-D focus is sharper in range than c/2B.
    assert 0.5 * S.range_resolution_mm(f) < along < S.range_resolution_mm(f)


def test_hann_window_lowers_cross_range_sidelobes():
    x_mm, y_mm = RP.aperture_axes(RADAR)
    f = RP.frequencies(RADAR)
    u0, v0, w0 = RP.view_frame("left") @ POINT
    u = u0 + np.linspace(-40, 40, 641)
    peak_sidelobe = {}
    for window in S.WINDOWS:
        cut = np.abs(S.focus(point_echo("left"), f, x_mm, y_mm, u, np.array([v0]), np.array([RADAR.z0_mm - w0]),
                             window))[0, 0]
        # Beyond both main lobes (Hann nulls at 2 lambda R / 2L = 7.2 mm).
        peak_sidelobe[window] = np.sort(cut[np.abs(u - u0) > 7.5])[-1] / cut.max()
    assert peak_sidelobe["none"] > 0.08  # rectangular: second sidelobe, -18 dB
    assert peak_sidelobe["hann"] < 0.04  # Hann: -31 dB and falling


def test_range_slices_cover_the_field_of_view():
    d = S.range_slices(300.0, 160.0, RP.frequencies(RADAR))
    assert d[0] == 220.0 and d[-1] == 380.0
    assert np.diff(d).max() <= S.range_resolution_mm(RP.frequencies(RADAR)) / S.SLICES_PER_RESOLUTION


@pytest.mark.parametrize("field, value", [("size", 0), ("fov_mm", -1.0), ("channels", ("colour",)),
                                          ("window", "hamming"), ("channels", ("depth", "depth")),
                                          ("depth_looks_mm", -1.0), ("depth_looks_mm", float("inf"))])
def test_bad_image_parameters_name_the_field(field, value):
    with pytest.raises(ValueError, match=f"{field}:"):
        S.ImageParams(**{field: value})


def test_channels_come_in_the_asked_order():
    x_mm, y_mm = RP.aperture_axes(RADAR)
    both = S.view_images(point_echo("superior"), RP.frequencies(RADAR), x_mm, y_mm, RADAR.z0_mm,
                         S.ImageParams(channels=("depth", "intensity")))
    assert both.shape == (2, 128, 128)
    assert both[1].max() == 1.0 and both[0].max() < 1.0


def test_multilook_depth_is_the_power_weighted_mean_of_its_neighbours():
    """Against a loop over every pixel's neighbours with Gaussian weights (scipy's 4-sigma radius)."""
    rng = np.random.default_rng(3)
    distance = rng.uniform(250, 350, (12, 9))
    power = rng.exponential(size=(12, 9)) * (rng.random((12, 9)) < 0.7)  # 0: not detected
    sigma = 1.3
    radius = int(4 * sigma + 0.5)
    expected = distance.copy()
    for r in range(12):
        for c in range(9):
            num = den = 0.0
            for rr in range(max(r - radius, 0), min(r + radius + 1, 12)):
                for cc in range(max(c - radius, 0), min(c + radius + 1, 9)):
                    g = np.exp(-((rr - r) ** 2 + (cc - c) ** 2) / (2 * sigma**2))
                    num += g * power[rr, cc] * distance[rr, cc]
                    den += g * power[rr, cc]
            if den > 0:
                expected[r, c] = num / den
    assert np.allclose(S.multilook_depth(distance, power, sigma), expected, rtol=0, atol=1e-9)
    alone = np.zeros_like(power)
    assert np.array_equal(S.multilook_depth(distance, alone, sigma), distance)  # nothing detected: unchanged


def naive_focus(echo, freqs, x_mm, y_mm, u_mm, v_mm, d_mm):
    """The module docstring's sums in complex128, slice by slice, on focus's padded grid, the pixels by DFT."""
    px, py, kx, ky, k, _, _ = S.spectral_grid(*echo.shape[:2], freqs, x_mm, y_mm, u_mm, v_mm)
    spectrum = np.fft.fft2(echo * S.aperture_window(*echo.shape[:2], "hann"), s=(px, py), axes=(0, 1))
    kz2 = 4 * k**2 - kx[:, None, None] ** 2 - ky[None, :, None] ** 2
    spectrum, kz = np.where(kz2 > 0, spectrum, 0), np.sqrt(np.maximum(kz2, 0))
    to_u, to_v = np.exp(1j * np.outer(u_mm - x_mm[0], kx)), np.exp(1j * np.outer(v_mm - y_mm[0], ky))
    return np.stack([to_v @ (spectrum * np.exp(-1j * kz * d)).sum(axis=2).T @ to_u.T for d in d_mm])


@pytest.mark.parametrize("fov_mm", [64.0, 67.2])  # 2 mm pixels: inverse FFTs onto them; 2.1 mm: a DFT
def test_focus_is_the_naive_sum(fov_mm):
    radar = RP.RadarParams(aperture=(16, 16), step_mm=4.0, n_samples=8)
    freqs, (x_mm, y_mm) = RP.frequencies(radar), RP.aperture_axes(radar)
    u_mm, v_mm = S.pixel_centres(32, fov_mm)
    lengths = S.spectral_grid(16, 16, freqs, x_mm, y_mm, u_mm, v_mm)[5:]
    assert (lengths == (66, 66)) if fov_mm == 64.0 else lengths == (None, None)
    rng = np.random.default_rng(3)
    echo = rng.standard_normal((16, 16, 8)) + 1j * rng.standard_normal((16, 16, 8))
    d_mm = S.range_slices(radar.z0_mm, fov_mm, freqs)
    truth = naive_focus(echo, freqs, x_mm, y_mm, u_mm, v_mm, d_mm)
    assert np.linalg.norm(S.focus(echo, freqs, x_mm, y_mm, u_mm, v_mm, d_mm) - truth) <= 1e-5 * np.linalg.norm(truth)


def test_default_images_take_inverse_ffts():
    freqs, (x_mm, y_mm) = RP.frequencies(RADAR), RP.aperture_axes(RADAR)
    grid = S.spectral_grid(*RADAR.aperture, freqs, x_mm, y_mm, *S.pixel_centres(IMAGES.size, IMAGES.fov_mm))
    assert grid[:2] == (165, 165) and grid[5:] == (264, 264)


@settings(max_examples=25, deadline=None)
@given(nx=st.integers(3, 20), ny=st.integers(3, 20), step=st.sampled_from([1.0, 2.0, 2.5, 4.0]),
       size=st.integers(2, 40), fov=st.sampled_from([20.0, 32.0, 40.0, 50.0, 64.0, 67.2, 100.0]))
def test_focus_is_the_naive_sum_on_grids_it_has_not_met(nx, ny, step, size, fov):
    """Apertures, steps and pixel grids of any shape (the FFTs where their sizes line up, else the DFTs)."""
    radar = RP.RadarParams(aperture=(nx, ny), step_mm=step, n_samples=4, echo_decimation=(1, 1, 1),
                           loss_decimation=(1, 1, 1))
    freqs, (x_mm, y_mm) = RP.frequencies(radar), RP.aperture_axes(radar)
    u_mm, v_mm = S.pixel_centres(size, fov)
    rng = np.random.default_rng(nx * ny * size)
    echo = rng.standard_normal((nx, ny, 4)) + 1j * rng.standard_normal((nx, ny, 4))
    d_mm = S.range_slices(radar.z0_mm, fov, freqs)
    truth = naive_focus(echo, freqs, x_mm, y_mm, u_mm, v_mm, d_mm)
    assert np.linalg.norm(S.focus(echo, freqs, x_mm, y_mm, u_mm, v_mm, d_mm) - truth) <= 1e-5 * np.linalg.norm(truth)


def test_depth_detection_takes_the_noise_rms_at_each_peaks_range():
    """Noise whose RMS changes with range, as a finite aperture's noise image does (0.8-1.27 of the whole at the
    defaults; 0.6-1.6 here, so that one image shows it): against
    the whole volume's RMS the strong slices' noise draws false depths; against each slice's own RMS noise passes
    as rarely as Rayleigh's law says (exp(-10^1.2) = 1.3e-7 a sample); a target 20 dB above its slice's noise is
    kept."""
    from meshsar_builder.radar.imaging import DETECTION_MARGIN_DB, ImageParams, range_slices, volume_images
    from meshsar_builder.radar.params import RadarParams, frequencies

    radar, images = RadarParams(), ImageParams(size=128)
    freqs = frequencies(radar)
    d = range_slices(radar.z0_mm, images.fov_mm, freqs)
    rms = np.linspace(1.6, 0.6, len(d))  # (S,)
    rng = np.random.default_rng(0)
    shape = (len(d), 128, 128)
    noise = (rng.normal(size=shape) + 1j * rng.normal(size=shape)) / np.sqrt(2) * rms[:, None, None]
    volume = noise.copy()
    volume[-3, 10, 10] = 10 ** (20 / 20) * rms[-3]  # a weak target at a quiet range
    volume[len(d) // 4, 40:44, 40:44] = 30.0  # the image's peak, 30 dB over the noise: inside the intensity floor
    whole = float(np.sqrt(np.mean(np.abs(noise) ** 2)))
    depth = {name: volume_images(volume.astype(np.complex64), freqs, radar.z0_mm, images, level)[1]
             for name, level in (("whole", whole), ("slices", rms))}
    assert DETECTION_MARGIN_DB == 12.0  # the rates above
    false = {name: int(np.count_nonzero(image)) - 17 for name, image in depth.items()}  # less the 16 + 1 targets
    assert false["slices"] <= 2 and false["whole"] >= 10, false  # measured 0 and 18
    assert depth["slices"][10, 10] != 0 and depth["slices"][41, 41] != 0
