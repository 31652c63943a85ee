"""One battery over the registry: round trips, validity, folds, gradients, reductions, errors."""

from __future__ import annotations

import math

import pytest
import torch

import omniscape_torch as ot
from omniscape_torch.cameras.radial import kannala_brandt_unproject
from omniscape_torch.cameras.scaramuzza import scaramuzza_project

from conftest import CASES, all_cases, directions_at, fibonacci_sphere

F64 = torch.float64
#: Round-trip tolerances of the issue: float64 to 1e-8 px and 1e-9 rad, float32 to 1e-3 px.
PX64, RAD64, PX32 = 1e-8, 1e-9, 1e-3
#: Model reductions (one model containing another) agree to 1e-6 px in float64 (the issue).
REDUCTION_PX = 1e-6
#: Keep round-trip samples this far (radians) inside a fold, where the inverse is
#: ill-conditioned: at a distance d from the fold, d theta ~ eps / (r'' d) (see test_fold_*).
FOLD_MARGIN = 1e-4
FOLD_MARGIN_32 = 1e-2


def model_and_params(name, params, dtype=F64):
    return ot.cameras.get_model(name), torch.tensor(params, dtype=dtype)


def angle_between(a, b):
    """Angle between unit vectors, accurate for tiny angles (atan2 of cross and dot)."""
    return torch.atan2(torch.linalg.vector_norm(torch.cross(a, b, dim=-1), dim=-1),
                       (a * b).sum(-1))


def theta_of(points):
    return torch.atan2(torch.linalg.vector_norm(points[..., :2], dim=-1), points[..., 2])


def domain_directions(model, params, n=6000):
    """Directions over the model's valid domain, away from the fold, plus special directions."""
    limit = float(model.max_angle(params))
    dirs = fibonacci_sphere(n)
    dirs = dirs[theta_of(dirs) < limit - FOLD_MARGIN]
    special = [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.6, 0.8, 0.0]]
    extra = directions_at(torch.tensor([1e-9, 1e-4, 0.3, limit - FOLD_MARGIN], dtype=F64))
    special = torch.tensor(special, dtype=F64)
    special = special[theta_of(special) < limit - FOLD_MARGIN]
    return torch.cat((dirs, special, extra))


# --------------------------------------------------------------------------------------------
# Registry
# --------------------------------------------------------------------------------------------

def test_registry_matches_design_table():
    # DESIGN.md's table, written out: name -> parameter order.
    design = {
        "pinhole": "fx fy cx cy", "equidistant": "fx fy cx cy", "equisolid": "fx fy cx cy",
        "stereographic": "fx fy cx cy", "orthographic": "fx fy cx cy",
        "kannala_brandt": "fx fy cx cy k1 k2 k3 k4",
        "unified": "fx fy cx cy xi k1 k2 p1 p2", "eucm": "fx fy cx cy alpha beta",
        "double_sphere": "fx fy cx cy xi alpha", "scaramuzza": "cx cy c d e a0",
        "equirectangular": "fx fy cx cy",
        "fov": "fx fy cx cy omega", "division": "fx fy cx cy k",
        "opencv": "fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4",
        "thin_prism_fisheye": "fx fy cx cy k1 k2 p1 p2 k3 k4 sx1 sy1",
        "fisheye624": "fx fy cx cy k0 k1 k2 k3 k4 k5 p0 p1 s0 s1 s2 s3",
        "woodscape": "cx cy aspect_ratio k1 k2 k3 k4",
    }
    assert list(ot.cameras.MODELS) == list(design)
    for name, names in design.items():
        model = ot.cameras.get_model(name)
        assert model.name == name
        assert model.param_names == tuple(names.split())
    assert ot.cameras.MODELS["scaramuzza"].variadic
    assert ot.cameras.MODELS["scaramuzza"].names_for(9)[-4:] == ("a0", "a1", "a2", "a3")
    assert set(CASES) == set(design)


def test_get_model_errors():
    with pytest.raises(ValueError, match="unknown camera model 'fishy'"):
        ot.cameras.get_model("fishy")
    with pytest.raises(TypeError, match="model"):
        ot.cameras.get_model(3)


# --------------------------------------------------------------------------------------------
# Round trips over the whole valid domain
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, params, size", all_cases())
def test_round_trip_from_rays_float64(name, params, size):
    model, p = model_and_params(name, params)
    dirs = domain_directions(model, p)
    pixels, valid = model.project(dirs, p)
    assert bool(valid.all()), f"{int((~valid).sum())} directions inside the domain flagged invalid"
    # Where the projection runs off to infinity (the unified model at its limit), compare the
    # directions that land within a few image sizes: those are the ones a camera can image.
    centre, _ = model.project(torch.tensor([0.0, 0.0, 1.0], dtype=F64), p)
    near = torch.linalg.vector_norm(pixels - centre, dim=-1) < 4 * max(size)
    dirs, pixels = dirs[near], pixels[near]
    rays, valid2 = model.unproject(pixels, p)
    assert bool(valid2.all())
    err = angle_between(rays, dirs)
    assert float(err.max()) < RAD64, float(err.max())
    torch.testing.assert_close(torch.linalg.vector_norm(rays, dim=-1),
                               torch.ones(len(rays), dtype=F64), atol=1e-12, rtol=0)


@pytest.mark.parametrize("name, params, size", all_cases())
def test_round_trip_from_pixels(name, params, size):
    model, p = model_and_params(name, params)
    h, w = size
    # The edge rows of an equirectangular image are its poles, where every pixel is one ray.
    lo = -0.5 if name != "equirectangular" else -0.49
    v, u = torch.meshgrid(torch.linspace(lo, h - 1 - lo, 61, dtype=F64),
                          torch.linspace(-0.5, w - 0.5, 61, dtype=F64), indexing="ij")
    pixels = torch.stack((u, v), -1).reshape(-1, 2)
    rays, valid = model.unproject(pixels, p)
    limit = model.max_angle(p)
    keep = valid & (theta_of(rays) < limit - FOLD_MARGIN)
    compared = int(keep.sum())
    assert compared > 100
    back, valid2 = model.project(rays[keep], p)
    assert bool(valid2.all())
    err = (back - pixels[keep]).abs()
    if name == "equirectangular":  # u = -0.5 and u = W - 0.5 are the same meridian
        err[:, 0] = torch.remainder(err[:, 0] + 1, w) - 1
    assert float(err.abs().max()) < PX64
    # float32 to 1e-3 px over the same pixels, kept 0.01 rad from a fold: there r'(theta) -> 0
    # and the float32 angle's rounding (1e-7 rad) moves the radius by 1e-7 / theta'(rho).
    keep32 = keep & (theta_of(rays) < limit - FOLD_MARGIN_32)
    p32 = p.float()
    rays32, v32 = model.unproject(pixels[keep32].float(), p32)
    back32, v32b = model.project(rays32, p32)
    ok = v32 & v32b
    assert int(ok.sum()) > 0.99 * int(keep32.sum())
    err32 = (back32[ok].double() - pixels[keep32][ok]).abs()
    if name == "equirectangular":
        err32[:, 0] = torch.remainder(err32[:, 0] + 1, w) - 1
    assert float(err32.abs().max()) < PX32


# --------------------------------------------------------------------------------------------
# Validity: exact domains, no folding, beyond 180 degrees
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, params, size", all_cases())
def test_validity_boundary_is_the_max_angle(name, params, size):
    """Just inside max_angle is valid, just outside invalid, and nothing beyond is valid."""
    model, p = model_and_params(name, params)
    limit = float(model.max_angle(p))
    inside = directions_at(torch.tensor([limit - 1e-6], dtype=F64))
    _, valid = model.project(inside, p)
    assert bool(valid.all())
    if limit < math.pi - 1e-6:
        theta = torch.linspace(limit + 1e-6, math.pi, 200, dtype=F64)
        _, valid = model.project(directions_at(theta), p)
        assert not bool(valid.any()), f"valid beyond the limit {math.degrees(limit):.3f} deg"


@pytest.mark.parametrize("name, params, size", all_cases())
def test_no_folding_radius_grows_with_angle(name, params, size):
    """Along a meridian, valid projections move monotonically away from the principal point:
    a point behind the camera never lands where a point in front does."""
    model, p = model_and_params(name, params)
    if name in ("equirectangular", "pinhole"):
        pytest.skip("no radial symmetry to test (covered by the round trips)")
    limit = float(model.max_angle(p))
    theta = torch.linspace(0.0, min(limit, math.pi) - 1e-7, 4001, dtype=F64)
    for phi in (0.0, 1.0, 2.5):
        dirs = torch.stack((torch.sin(theta) * math.cos(phi), torch.sin(theta) * math.sin(phi),
                            torch.cos(theta)), -1)
        pixels, valid = model.project(dirs, p)
        assert bool(valid.all())
        centre, _ = model.project(torch.tensor([0.0, 0.0, 1.0], dtype=F64), p)
        r = torch.linalg.vector_norm(pixels - centre, dim=-1)
        assert bool((r[1:] > r[:-1]).all()), "projection radius must grow with the angle"


@pytest.mark.parametrize("name, params", [
    ("equidistant", [200.0, 200.0, 0.0, 0.0]),
    ("kannala_brandt", [200.0, 200.0, 0.0, 0.0, -0.02, 0.004, -0.001, 0.0002]),
    ("unified", [300.0, 300.0, 0.0, 0.0, 1.6, 0.0, 0.0, 0.0, 0.0]),
    ("eucm", [220.0, 220.0, 0.0, 0.0, 0.6, 1.1]),
    ("double_sphere", [160.0, 160.0, 0.0, 0.0, -0.2, 0.6]),
    ("scaramuzza", None),
    ("division", [400.0, 400.0, 0.0, 0.0, -0.3]),
    # decentring shifts the 90-degree curve by ~3 px per 1e-3 of p: small p and s here
    ("thin_prism_fisheye", [200.0, 200.0, 0.0, 0.0, -0.02, 0.004, 1e-4, -2e-4, -0.001, 0.0002,
                            5e-5, -3e-5]),
    ("fisheye624", [200.0, 200.0, 0.0, 0.0, -0.02, 0.003, -2e-4, 1e-5, 0.0, 0.0, 4e-4, -3e-4,
                    2e-4, 1e-5, -3e-4, 2e-5]),
    ("woodscape", [0.0, 0.0, 1.0, 339.749, -31.988, 48.275, -7.201]),   # front.json's lens
])
def test_beyond_180_degrees(name, params):
    """Models whose domain passes 90 degrees keep points behind the camera (z < 0) valid up to
    their limit and place them farther out than every point in front."""
    if params is None:
        params = CASES["scaramuzza"][0][0]
    model, p = model_and_params(name, params)
    limit = float(model.max_angle(p))
    assert limit > math.pi / 2 + 0.1
    behind = directions_at(torch.linspace(math.pi / 2 + 0.01, limit - 1e-3, 50, dtype=F64))
    front = directions_at(torch.linspace(0, math.pi / 2, 50, dtype=F64))
    assert bool((behind[:, 2] < 0).all())
    pb, vb = model.project(behind, p)
    pf, vf = model.project(front, p)
    assert bool(vb.all()) and bool(vf.all())
    centre = model.project(torch.tensor([0.0, 0.0, 1.0], dtype=F64), p)[0]
    rb = torch.linalg.vector_norm(pb - centre, dim=-1)
    rf = torch.linalg.vector_norm(pf - centre, dim=-1)
    assert float(rb.min()) > float(rf.max())


def test_limits_match_published_formulas():
    """max_angle against the closed forms written independently here."""
    def angle(name, params):
        return float(ot.cameras.get_model(name).max_angle(torch.tensor(params, dtype=F64)))
    assert angle("pinhole", [1, 1, 0, 0]) == pytest.approx(math.pi / 2)
    assert angle("orthographic", [1, 1, 0, 0]) == pytest.approx(math.pi / 2)
    for xi in (0.3, 0.9, 1.0, 1.6, 3.0):
        w = xi if xi <= 1 else 1 / xi
        assert angle("unified", [1, 1, 0, 0, xi, 0, 0, 0, 0]) == pytest.approx(math.acos(-w))
    # Kannala-Brandt fold: dr/dtheta = 1 - 0.36 t + 0.025 t^2 with t = theta^2 (k1=-0.12,
    # k2=0.005): t = (0.36 - sqrt(0.36^2 - 0.1)) / 0.05.
    t = (0.36 - math.sqrt(0.36 ** 2 - 4 * 0.025)) / (2 * 0.025)
    assert angle("kannala_brandt", [1, 1, 0, 0, -0.12, 0.005, 0, 0]) == pytest.approx(
        math.sqrt(t), rel=1e-12)
    # EUCM alpha=0.6, beta=1.1: w = 0.4/0.6; boundary z = -w sqrt(beta rho^2 + z^2).
    w = 0.4 / 0.6
    theta = math.pi - math.atan(math.sqrt((1 - w * w) / (w * w * 1.1)))
    assert angle("eucm", [1, 1, 0, 0, 0.6, 1.1]) == pytest.approx(theta, rel=1e-12)
    z = math.cos(theta)
    assert z == pytest.approx(-w * math.sqrt(1.1 * math.sin(theta) ** 2 + z * z))
    # Double sphere: acos(-w2), w2 = (w1 + xi) / sqrt(2 w1 xi + xi^2 + 1).
    w1 = 0.4 / 0.6
    w2 = (w1 - 0.2) / math.sqrt(2 * w1 * -0.2 + 0.04 + 1)
    assert angle("double_sphere", [1, 1, 0, 0, -0.2, 0.6]) == pytest.approx(math.acos(-w2))
    # Division: the ray (rd, 1 + k rd^2) turns back at rd^2 = 1 / k (k > 0): atan(1 / (2 sqrt k))
    assert angle("division", [1, 1, 0, 0, 0.3]) == pytest.approx(math.atan(0.5 / math.sqrt(0.3)))
    assert angle("division", [1, 1, 0, 0, -0.3]) == pytest.approx(math.pi)
    assert angle("division", [1, 1, 0, 0, 0.0]) == pytest.approx(math.pi / 2)
    assert angle("fov", [1, 1, 0, 0, 0.9]) == pytest.approx(math.pi / 2)
    # OpenCV (k1=-0.35, k2=0.05): d(r (1 + k1 t + k2 t^2)) / dr = 1 - 1.05 t + 0.25 t^2
    t = (1.05 - math.sqrt(1.05 ** 2 - 1.0)) / 0.5
    assert angle("opencv", [1, 1, 0, 0, -0.35, 0.05] + [0] * 10) == pytest.approx(
        math.atan(math.sqrt(t)), rel=1e-12)
    # ... and with the rational denominator's pole first: 1 + k4 t = 0 at t = 0.5 (k4 = -2)
    assert angle("opencv", [1, 1, 0, 0, 0, 0, 0, 0, 0, -2.0] + [0] * 6) <= math.atan(
        math.sqrt(0.5)) + 1e-12
    # The fisheyes: Kannala-Brandt's fold (k1=-0.12, k2=0.005) in their own coefficient orders
    t = (0.36 - math.sqrt(0.36 ** 2 - 4 * 0.025)) / (2 * 0.025)
    assert angle("fisheye624", [1, 1, 0, 0, -0.12, 0.005] + [0] * 10) == pytest.approx(
        math.sqrt(t), rel=1e-12)
    assert angle("thin_prism_fisheye", [1, 1, 0, 0, -0.12, 0.005] + [0] * 6) == pytest.approx(
        math.sqrt(t), rel=1e-12)


@pytest.mark.parametrize("name, params, size", [
    pytest.param("kannala_brandt", CASES["kannala_brandt"][2][0], None, id="kannala_brandt"),
    pytest.param("scaramuzza", CASES["scaramuzza"][1][0], None, id="scaramuzza"),
    pytest.param("unified", [300.0, 300.0, 0.0, 0.0, 0.9, -0.4, 0.05, 0.0, 0.0], None,
                 id="unified-distortion"),
    pytest.param("opencv", CASES["opencv"][2][0], None, id="opencv"),
    pytest.param("fisheye624", CASES["fisheye624"][1][0], None, id="fisheye624"),
    pytest.param("thin_prism_fisheye", CASES["thin_prism_fisheye"][1][0], None,
                 id="thin_prism_fisheye"),
    pytest.param("woodscape", CASES["woodscape"][1][0], None, id="woodscape"),
])
def test_fold_iterative_inverse_converges_up_to_the_fold(name, params, size):
    """The iterative inverses reach the float64 tolerance up to 1e-6 rad before the fold; past
    the fold's image the pixels are invalid, never garbage."""
    model, p = model_and_params(name, params)
    limit = float(model.max_angle(p))
    theta = limit - torch.logspace(-1, -6, 30, dtype=F64)
    dirs = directions_at(theta, 8)
    pixels, valid = model.project(dirs, p)
    assert bool(valid.all())
    rays, valid = model.unproject(pixels, p)
    assert bool(valid.all())
    err = angle_between(rays, dirs)
    # conditioning: near the fold r(theta) ~ r_max - c (limit - theta)^2, so a pixel rounding
    # error eps_px moves theta by eps_px / (2 c (limit - theta)); 1e-9 rad holds at 1e-6 rad.
    assert float(err.max()) < RAD64, float(err.max())
    # pixels beyond the fold's radius are invalid
    edge = model.project(directions_at(torch.tensor([limit - 1e-9], dtype=F64), 8), p)[0]
    centre = model.project(torch.tensor([0.0, 0.0, 1.0], dtype=F64), p)[0]
    beyond = centre + (edge - centre) * 1.001
    _, valid = model.unproject(beyond, p)
    assert not bool(valid.any())


def test_iteration_count_is_fixed_and_non_convergence_is_invalid():
    params = torch.tensor(CASES["kannala_brandt"][1][0], dtype=F64)
    pixels = torch.tensor([[319.5 + r, 319.5] for r in (10.0, 150.0, 290.0, 310.0)], dtype=F64)
    full, valid_full = kannala_brandt_unproject(pixels, params)
    assert bool(valid_full.all())
    few, valid_few = kannala_brandt_unproject(pixels, params, iterations=3)
    assert not bool(valid_few.all()), "three Newton steps cannot converge everywhere"
    assert bool(valid_few.any()), "but they do converge for some lanes"
    assert bool(torch.isfinite(few).all())
    # lanes flagged converged after three steps are indeed converged
    assert float(angle_between(few[valid_few], full[valid_few]).max()) < RAD64


@pytest.mark.parametrize("name", ["opencv", "thin_prism_fisheye", "fisheye624"])
def test_2d_newton_iteration_count_is_fixed_and_non_convergence_is_invalid(name):
    """The 2-D Newton undistortion (tangential and thin-prism terms): one step does not converge
    everywhere, the lanes it flags converged are, and every lane is finite."""
    model, p = model_and_params(name, CASES[name][0][0])
    dirs = directions_at(torch.tensor([0.05, 0.4, 0.8, 1.2], dtype=F64), 8)
    pixels, valid = model.project(dirs, p)
    pixels = pixels[valid]
    full, valid_full = model.unproject(pixels, p)
    assert bool(valid_full.all())
    few, valid_few = model.unproject(pixels, p, iterations=1)
    assert not bool(valid_few.all()), "one Newton step cannot converge everywhere"
    assert bool(torch.isfinite(few).all())
    if bool(valid_few.any()):
        assert float(angle_between(few[valid_few], full[valid_few]).max()) < RAD64


# --------------------------------------------------------------------------------------------
# Values and gradients finite everywhere; gradcheck at the hard places
# --------------------------------------------------------------------------------------------

HARD_POINTS = torch.tensor([
    [0.0, 0.0, 1.0],     # optical axis
    [0.0, 0.0, -1.0],    # straight behind
    [0.0, 0.0, 0.0],     # origin
    [1.0, 0.0, 0.0],     # z = 0
    [0.3, -0.4, 0.0],    # z = 0
    [1e-30, 0.0, 1.0],   # next to the axis
    [0.2, 0.1, -1.0],    # behind
    [1e6, -2e6, 3e5],    # far
], dtype=F64)


@pytest.mark.parametrize("name, params, size", all_cases())
def test_values_and_gradients_finite_everywhere(name, params, size):
    model, p = model_and_params(name, params)
    pts = HARD_POINTS.clone().requires_grad_(True)
    pp = p.clone().requires_grad_(True)
    pixels, valid = model.project(pts, pp)
    assert bool(torch.isfinite(pixels).all())
    gp, gq = torch.autograd.grad(pixels.sum(), (pts, pp))
    assert bool(torch.isfinite(gp).all()) and bool(torch.isfinite(gq).all())

    h, w = size
    centre = name in ("scaramuzza", "woodscape")   # the models with cx, cy first
    pix = torch.tensor([[p[0] if centre else p[2], p[1] if centre else p[3]],
                        [-0.5, -0.5], [w - 0.5, h - 0.5], [1e5, -1e5], [0.0, h / 2]],
                       dtype=F64).requires_grad_(True)
    rays, valid = model.unproject(pix, pp)
    assert bool(torch.isfinite(rays).all())
    gr, gq = torch.autograd.grad(rays.sum(), (pix, pp))
    assert bool(torch.isfinite(gr).all()) and bool(torch.isfinite(gq).all())
    assert bool(valid[0]), "the principal point must be valid"


def _gradcheck_points(name, params, size):
    """Points for gradcheck: the optical axis (exactly), z = 0 where valid, behind the camera
    where valid, the edge of the image circle (0.02 rad inside the model's limit, where that
    lands within a few image sizes), and a generic point."""
    if name == "equirectangular":  # poles and the +-pi seam are where it is not smooth
        return torch.tensor([[0.3, -0.2, 1.5], [0.1, 0.5, -1.0], [0.7, 0.4, 0.0]], dtype=F64)
    model, p = model_and_params(name, params)
    limit = float(model.max_angle(p))
    pts = [[0.0, 0.0, 2.0], [0.3, -0.2, 1.5]]
    if limit > math.pi / 2 + 1e-9:
        pts.append([0.7, 0.4, 0.0])
    if limit > math.pi / 2 + 0.1:
        th = 0.5 * (math.pi / 2 + min(limit, math.pi))
        pts.append([math.sin(th) * 0.8, math.sin(th) * -0.6, math.cos(th)])
    th = min(limit, math.pi) - 0.02
    edge = torch.tensor([[math.sin(th) * 0.6, math.sin(th) * 0.8, math.cos(th)]], dtype=F64)
    px, _ = model.project(edge, p)
    centre, _ = model.project(torch.tensor([0.0, 0.0, 1.0], dtype=F64), p)
    if float((px - centre).norm()) < 4 * max(size):
        pts.append(edge[0].tolist())
    return torch.tensor(pts, dtype=F64)


def _param_scale(p):
    """Gradcheck perturbs every input by 1e-6; a polynomial coefficient of 1e-10 multiplying
    rho^4 ~ 1e12 is then perturbed far outside the linear regime. Checking the gradient with
    respect to relative perturbations ``params = p + s * |p|`` (``1e-3`` for zero entries) is the
    same chain rule with every direction in its linear range."""
    return torch.where(p != 0, p.abs(), torch.full_like(p, 1e-3))


@pytest.mark.parametrize("name, params, size", all_cases())
def test_gradcheck_project(name, params, size):
    model, p = model_and_params(name, params)
    pts = _gradcheck_points(name, params, size)
    assert bool(model.project(pts, p)[1].all())
    scale = _param_scale(p)
    torch.autograd.gradcheck(lambda x, s: model.project(x, p + s * scale)[0],
                             (pts.requires_grad_(True), torch.zeros_like(p, requires_grad=True)))


@pytest.mark.parametrize("name, params, size", all_cases())
def test_gradcheck_unproject(name, params, size):
    model, p = model_and_params(name, params)
    pts = _gradcheck_points(name, params, size)
    pixels, valid = model.project(pts, p)
    assert bool(valid.all())
    scale = _param_scale(p)
    torch.autograd.gradcheck(lambda x, s: model.unproject(x, p + s * scale)[0],
                             (pixels.requires_grad_(True), torch.zeros_like(p, requires_grad=True)))


# --------------------------------------------------------------------------------------------
# Model reductions (one model contains another)
# --------------------------------------------------------------------------------------------

def _compare(model_a, pa, model_b, pb, dirs):
    a, va = ot.cameras.get_model(model_a).project(dirs, torch.tensor(pa, dtype=F64))
    b, vb = ot.cameras.get_model(model_b).project(dirs, torch.tensor(pb, dtype=F64))
    both = va & vb
    assert bool((va == vb).all()), "the two models disagree on validity"
    compared = int(both.sum())
    assert compared > 0
    assert float((a[both] - b[both]).abs().max()) < REDUCTION_PX
    ra, _ = ot.cameras.get_model(model_a).unproject(a[both], torch.tensor(pa, dtype=F64))
    rb, _ = ot.cameras.get_model(model_b).unproject(a[both], torch.tensor(pb, dtype=F64))
    assert float(angle_between(ra, rb).max()) < RAD64
    return compared


def test_reduction_kannala_brandt_k0_is_equidistant():
    dirs = fibonacci_sphere(3000)
    assert _compare("kannala_brandt", [200, 210, 320, 300, 0, 0, 0, 0],
                    "equidistant", [200, 210, 320, 300], dirs) > 0


def test_reduction_unified_xi0_is_pinhole():
    dirs = fibonacci_sphere(3000)
    assert _compare("unified", [400, 410, 320, 300, 0, 0, 0, 0, 0],
                    "pinhole", [400, 410, 320, 300], dirs) > 0


@pytest.mark.parametrize("alpha", [0.2, 0.5, 0.7])
def test_reduction_double_sphere_xi0_is_unified(alpha):
    # alpha form of the unified model: xi = alpha / (1 - alpha), gamma = f / (1 - alpha)
    dirs = fibonacci_sphere(3000)
    xi, scale = alpha / (1 - alpha), 1 / (1 - alpha)
    assert _compare("double_sphere", [200, 210, 320, 300, 0.0, alpha],
                    "unified", [200 * scale, 210 * scale, 320, 300, xi, 0, 0, 0, 0], dirs) > 0


@pytest.mark.parametrize("alpha", [0.2, 0.5, 0.7])
def test_reduction_eucm_beta1_is_unified(alpha):
    dirs = fibonacci_sphere(3000)
    xi, scale = alpha / (1 - alpha), 1 / (1 - alpha)
    assert _compare("eucm", [200, 210, 320, 300, alpha, 1.0],
                    "unified", [200 * scale, 210 * scale, 320, 300, xi, 0, 0, 0, 0], dirs) > 0


@pytest.mark.parametrize("ks", [(-0.02, 0.004, -0.001, 0.0002), (-0.12, 0.005, 0.0, 0.0)])
def test_reduction_fisheye624_without_tangential_and_prism_is_kannala_brandt(ks):
    """fisheye624's k0..k3 are Kannala-Brandt's k1..k4 (theta^3 .. theta^9); k4 = k5 = 0 and
    p = s = 0 leave the rest; the second lens folds (the same fold on both sides)."""
    dirs = fibonacci_sphere(3000)
    assert _compare("fisheye624", [200, 210, 320, 300, *ks, 0, 0, 0, 0, 0, 0, 0, 0],
                    "kannala_brandt", [200, 210, 320, 300, *ks], dirs) > 0


@pytest.mark.parametrize("ks", [(-0.02, 0.004, -0.001, 0.0002), (-0.12, 0.005, 0.0, 0.0)])
def test_reduction_thin_prism_fisheye_without_p_and_s_is_kannala_brandt(ks):
    """THIN_PRISM_FISHEYE's order is k1, k2, p1, p2, k3, k4, sx1, sy1."""
    k1, k2, k3, k4 = ks
    dirs = fibonacci_sphere(3000)
    assert _compare("thin_prism_fisheye", [200, 210, 320, 300, k1, k2, 0, 0, k3, k4, 0, 0],
                    "kannala_brandt", [200, 210, 320, 300, *ks], dirs) > 0


def test_reduction_opencv_and_division_undistorted_are_pinhole():
    dirs = fibonacci_sphere(3000)
    dirs = dirs[dirs[:, 2] > 0.05]   # pinhole pixels beyond ~87 degrees run to 1e4 px and more
    assert _compare("opencv", [400, 410, 320, 300] + [0] * 12,
                    "pinhole", [400, 410, 320, 300], dirs) > 0
    assert _compare("division", [400, 410, 320, 300, 0.0],
                    "pinhole", [400, 410, 320, 300], dirs) > 0


def test_reduction_fov_omega_to_zero_is_pinhole():
    """omega = 0 is the pinhole exactly; as omega -> 0 the FOV model approaches it as omega^2
    (its factor is 1 + omega^2 / 12 - omega^2 r^2 / 3 + ...)."""
    dirs = fibonacci_sphere(3000)
    dirs = dirs[dirs[:, 2] > 0.5]   # within 60 degrees: r <= sqrt(3)
    pin, _ = ot.cameras.get_model("pinhole").project(dirs, torch.tensor([400.0, 410, 320, 300],
                                                                       dtype=F64))
    assert _compare("fov", [400, 410, 320, 300, 0.0], "pinhole", [400, 410, 320, 300], dirs) > 0
    ratios = []
    for omega in (1e-2, 1e-3, 1e-4):
        px, valid = ot.cameras.get_model("fov").project(
            dirs, torch.tensor([400.0, 410, 320, 300, omega], dtype=F64))
        assert bool(valid.all())
        ratios.append(float((px - pin).abs().max()) / omega ** 2)
    # the omega^2 coefficient: max over r <= sqrt(3) of f r |1/12 - r^2 / 3| ~ 9e2 px
    assert max(ratios) < 1e3 and max(ratios) / min(ratios) < 1.01, ratios


def test_equidistant_analytic():
    """r = f theta, written out: 90 degrees lands f pi / 2 pixels from the centre."""
    model, p = model_and_params("equidistant", [200.0, 150.0, 10.0, 20.0])
    for theta, phi in ((0.0, 0.0), (math.pi / 2, 0.0), (2.0, 1.0), (3.0, -2.0)):
        d = torch.tensor([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi),
                          math.cos(theta)], dtype=F64)
        px, valid = model.project(d, p)
        expected = [10 + 200 * theta * math.cos(phi), 20 + 150 * theta * math.sin(phi)]
        assert bool(valid)
        torch.testing.assert_close(px, torch.tensor(expected, dtype=F64), atol=1e-10, rtol=0)


def test_equirectangular_convention():
    """lon = atan2(x, z) to the right, lat positive downwards (y down); the seam at +-pi."""
    model, p = model_and_params("equirectangular", [100.0, 100.0, 314.0, 157.0])
    dirs = torch.tensor([[0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], dtype=F64)
    px, valid = model.project(dirs, p)
    assert bool(valid.all())
    expected = [[314, 157], [314 + 50 * math.pi, 157], [314, 157 + 50 * math.pi],
                [314 - 50 * math.pi, 157], [314, 157 - 50 * math.pi]]
    torch.testing.assert_close(px, torch.tensor(expected, dtype=F64), atol=1e-9, rtol=0)


# --------------------------------------------------------------------------------------------
# Barreto-Araujo mirrors, checked against a ray-traced mirror
# --------------------------------------------------------------------------------------------

def _trace_hyperbolic(v, d, p, f):
    """Image radius of direction ``v`` (unit, from the mirror focus F1 = 0) seen in a hyperbolic
    mirror whose second focus F2 = (0, 0, -d) holds a pinhole of focal f looking up +z.

    The mirror is the sheet |P - F2| - |P - F1| = 2a around F1 (semi-latus rectum b^2/a = 2p,
    c = d/2): P = t v with t = (d^2 - 4a^2) / (4a + 2 d v_z') where v_z' = -v_z (v_z measured
    along the unified axis, which points from F1 towards the camera).
    """
    c = d / 2
    # b^2 = c^2 - a^2 and b^2 / a = 2 p  ->  a^2 + 2 p a - c^2 = 0
    a = -p + math.sqrt(p * p + c * c)
    vz_up = -v[2]  # mirror frame: +z up, away from the camera
    t = (d * d - 4 * a * a) / (4 * a - 2 * d * vz_up)
    px, py, pz = t * v[0], t * v[1], t * vz_up
    return f * math.hypot(px, py) / (pz + d)


def test_unified_from_mirror_hyperbolic_matches_ray_tracing():
    d, p, f = 0.1, 0.02, 800.0
    params = ot.cameras.unified_from_mirror("hyperbolic", d=d, p=p, focal=f, cx=0.0, cy=0.0)
    model = ot.cameras.get_model("unified")
    compared = 0
    for theta in torch.linspace(0.0, 1.9, 40, dtype=F64):
        v = [math.sin(theta), 0.0, math.cos(theta)]
        px, valid = model.project(torch.tensor(v, dtype=F64), params)
        if not bool(valid):
            continue
        traced = _trace_hyperbolic(v, d, p, f)
        assert float(px[0]) == pytest.approx(traced, rel=1e-10, abs=1e-9)
        compared += 1
    assert compared > 30


def test_unified_from_mirror_parabolic_matches_ray_tracing():
    # parabola with focus at 0: |P| = 2p / (1 + cos(phi)), phi from the vertex direction;
    # an orthographic camera of s pixels per unit sees the radius s |P| sin(phi).
    p, s = 0.03, 5000.0
    params = ot.cameras.unified_from_mirror("parabolic", p=p, focal=s, cx=0.0, cy=0.0)
    model = ot.cameras.get_model("unified")
    for phi in (0.0, 0.5, 1.5, 2.5, 3.0):
        px, valid = model.project(torch.tensor([math.sin(phi), 0.0, math.cos(phi)], dtype=F64),
                                  params)
        assert bool(valid)
        assert float(px[0]) == pytest.approx(s * 2 * p / (1 + math.cos(phi)) * math.sin(phi),
                                             rel=1e-12, abs=1e-9)


def test_unified_from_mirror_errors():
    with pytest.raises(ValueError, match="mirror"):
        ot.cameras.unified_from_mirror("conical", p=1.0, focal=1.0, cx=0, cy=0)
    with pytest.raises(ValueError, match="p, d"):
        ot.cameras.unified_from_mirror("hyperbolic", p=0.1, d=0.0, focal=1.0, cx=0, cy=0)
    planar = ot.cameras.unified_from_mirror("planar", focal=300.0, cx=1.0, cy=2.0)
    assert planar.tolist() == [300.0, 300.0, 1.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0]


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------

def test_bad_input_messages():
    model = ot.cameras.get_model("kannala_brandt")
    p = torch.tensor(CASES["kannala_brandt"][1][0], dtype=F64)
    with pytest.raises(ValueError, match=r"points: expected shape \(\.\.\., 3\)"):
        model.project(torch.zeros(5, 2, dtype=F64), p)
    with pytest.raises(ValueError, match="takes 8 or 9 parameters"):
        model.project(torch.zeros(5, 3, dtype=F64), p[:6])
    with pytest.raises(ValueError, match=r"pixels: expected shape \(\.\.\., 2\)"):
        model.unproject(torch.zeros(5, 3, dtype=F64), p)
    with pytest.raises(TypeError, match="same dtype"):
        model.project(torch.zeros(5, 3), p)
    with pytest.raises(TypeError, match="floating-point"):
        model.project(torch.zeros(5, 3, dtype=torch.long), p)
    with pytest.raises(ValueError, match="do not broadcast"):
        model.project(torch.zeros(5, 3, dtype=F64), p.expand(4, 8))
    with pytest.raises(ValueError, match="at least 6"):
        ot.cameras.get_model("scaramuzza").unproject(torch.zeros(2, 2, dtype=F64),
                                                     torch.zeros(5, dtype=F64))


@pytest.mark.parametrize("name, params, match", [
    ("pinhole", [-1.0, 1.0, 0.0, 0.0], "fx of the pinhole model must be > 0"),
    ("equidistant", [1.0, math.nan, 0.0, 0.0], "must be finite"),
    ("kannala_brandt", [1.0, 1.0, 0.0, 0.0, math.inf, 0.0, 0.0, 0.0], "must be finite"),
    ("unified", [1.0, 1.0, 0.0, 0.0, -0.5, 0, 0, 0, 0], "xi of the unified model"),
    ("eucm", [1.0, 1.0, 0.0, 0.0, 1.5, 1.0], "alpha of the eucm model"),
    ("eucm", [1.0, 1.0, 0.0, 0.0, 0.5, -1.0], "beta of the eucm model must be > 0"),
    ("double_sphere", [1.0, 1.0, 0.0, 0.0, 0.1, 1.2], "alpha of the double_sphere model"),
    ("scaramuzza", [0.0, 0.0, 1.0, 0.0, 0.0, 100.0, 0.0], "a0 of the scaramuzza model"),
    ("pinhole", [1.0, 1.0, 0.0], "takes 4 parameters"),
    ("fov", [1.0, 1.0, 0.0, 0.0, -0.1], "omega of the fov model must lie in"),
    ("fov", [1.0, 1.0, 0.0, 0.0, 4.0], "omega of the fov model must lie in"),
    ("division", [0.0, 1.0, 0.0, 0.0, 0.1], "fx of the division model must be > 0"),
    ("opencv", [1.0, -1.0, 0.0, 0.0] + [0.0] * 12, "fy of the opencv model must be > 0"),
    ("fisheye624", [1.0, 1.0, 0.0, 0.0] + [0.0] * 11, "takes 16 parameters"),
    ("thin_prism_fisheye", [1.0, 1.0, 0.0, 0.0] + [math.nan] + [0.0] * 7, "k1 .* must be finite"),
    ("woodscape", [0.0, 0.0, 0.0, 300.0, 0.0, 0.0, 0.0], "aspect_ratio of the woodscape model"),
    ("woodscape", [0.0, 0.0, 1.0, -300.0, 0.0, 0.0, 0.0], "k1 of the woodscape model must be"),
])
def test_camera_rejects_bad_params(name, params, match):
    with pytest.raises(ValueError, match=match):
        ot.Camera(name, params, (10, 10))


@pytest.mark.parametrize("kwargs, error, match", [
    (dict(image_size=(10,)), ValueError, "image_size"),
    (dict(image_size=(10, 0)), ValueError, "W must be a positive int"),
    (dict(image_size=(10.5, 10)), ValueError, "H must be a positive int"),
    (dict(fov=190.0), ValueError, r"did you mean math.radians\(190.0\)"),
    (dict(fov=-1.0), ValueError, "fov"),
    (dict(params="abc"), TypeError, "params"),
    (dict(params=torch.tensor([1, 1, 0, 0])), TypeError, "floating-point"),
])
def test_camera_rejects_bad_arguments(kwargs, error, match):
    args = dict(model="equidistant", params=[1.0, 1.0, 0.0, 0.0], image_size=(10, 10))
    args.update(kwargs)
    with pytest.raises(error, match=match):
        ot.Camera(**args)


# --------------------------------------------------------------------------------------------
# Camera module
# --------------------------------------------------------------------------------------------

def test_ray_grid_pixel_centres_and_bounds():
    """(0, 0) is the centre of the top-left pixel; the image spans [-0.5, W - 0.5]."""
    cam = ot.Camera("pinhole", torch.tensor([2.0, 2.0, 1.5, 0.5], dtype=F64), (2, 4))
    rays, valid = cam.ray_grid()
    assert rays.shape == (2, 4, 3) and valid.shape == (2, 4) and bool(valid.all())
    # pixel (u=0, v=0) is the ray through ((0 - 1.5) / 2, (0 - 0.5) / 2, 1)
    expected = torch.tensor([-0.75, -0.25, 1.0], dtype=F64)
    torch.testing.assert_close(rays[0, 0], expected / expected.norm())
    on_edge = torch.tensor([[-0.5, -0.5], [3.5, 1.5], [-0.5001, 0.0], [0.0, 1.5001]], dtype=F64)
    _, valid = cam.unproject(on_edge)
    assert valid.tolist() == [True, True, False, False]


def test_fov_masks_the_cone():
    params = torch.tensor([100.0, 100.0, 99.5, 99.5], dtype=F64)
    cam = ot.Camera("equidistant", params, (200, 200), fov=math.radians(120))
    rays, valid = cam.ray_grid()
    theta = theta_of(rays)
    assert bool((theta[valid] <= math.radians(60) + 1e-12).all())
    # equidistant: theta = r / f exactly, so the mask is the disc r <= f * 60 deg
    v, u = torch.meshgrid(torch.arange(200, dtype=F64), torch.arange(200, dtype=F64),
                          indexing="ij")
    r = torch.hypot(u - 99.5, v - 99.5)
    assert torch.equal(valid, r <= 100 * math.radians(60) + 1e-9)
    assert float(cam.field_of_view()) == pytest.approx(2 * float(r[valid].max()) / 100)


def test_batched_cameras_and_learnable_gradients():
    params = torch.tensor([[200.0, 200.0, 31.5, 23.5, 0.0, 0.0, 0.0, 0.0],
                           [150.0, 160.0, 32.0, 24.0, -0.01, 0.0, 0.0, 0.0]], dtype=F64)
    cam = ot.Camera("kannala_brandt", params, (48, 64), learnable=True)
    rays, valid = cam.ray_grid()
    assert rays.shape == (2, 48, 64, 3) and valid.shape == (2, 48, 64)
    for b in range(2):
        single = ot.Camera("kannala_brandt", params[b], (48, 64))
        r1, v1 = single.ray_grid()
        torch.testing.assert_close(rays[b].detach(), r1)
        assert torch.equal(valid[b], v1)
    rays[..., 0].sum().backward()
    assert cam.params.grad is not None and bool(torch.isfinite(cam.params.grad).all())
    assert float(cam.params.grad[:, :4].abs().sum()) > 0
    with pytest.raises(ValueError, match="camera batch of shape"):
        cam.project(torch.zeros(3, 5, 3, dtype=F64))


def test_angular_resolution_equidistant_analytic():
    """Equidistant: f px/rad radially everywhere; tangentially f theta / sin(theta)."""
    f = 100.0
    cam = ot.Camera("equidistant", torch.tensor([f, f, 99.5, 99.5], dtype=F64), (200, 200))
    res = cam.angular_resolution()
    assert float(res["center"]) == pytest.approx(f, rel=1e-4)
    theta = float(res["edge_angle"])
    assert float(res["edge_coarsest"]) == pytest.approx(f, rel=1e-4)
    assert float(res["edge_finest"]) == pytest.approx(f * theta / math.sin(theta), rel=1e-4)


def test_camera_repr_and_names():
    cam = ot.Camera.from_ocamcalib(__import__("conftest").OCAMCALIB_FILE)
    assert "scaramuzza" in repr(cam)
    assert cam.param_names == ("cx", "cy", "c", "d", "e", "a0", "a1", "a2", "a3", "a4")


def test_scaramuzza_invpol_is_ocamcalib_world2cam_formula():
    """With invpol, rho = sum invpol_i t^i at t = atan(-z / rho_xy): written out for one point."""
    cam = ot.Camera.from_ocamcalib(__import__("conftest").OCAMCALIB_FILE)
    x, y, z = 0.3, -0.4, 0.5
    t = math.atan(-z / math.hypot(x, y))
    rho = sum(c * t ** i for i, c in enumerate(cam.invpol.tolist()))
    cx, cy, c, d, e = cam.params[:5].tolist()
    pu, pv = rho * x / math.hypot(x, y), rho * y / math.hypot(x, y)
    px, valid = scaramuzza_project(torch.tensor([x, y, z], dtype=F64), cam.params,
                                   invpol=cam.invpol)
    assert bool(valid)
    assert px.tolist() == pytest.approx([pu + e * pv + cx, d * pu + c * pv + cy], abs=1e-9)


def test_blind_fov_masks_the_central_cone():
    """A catadioptric camera's own reflection: the disc r < f * blind/2 is invalid (equidistant:
    theta = r / f exactly), the annulus up to fov/2 valid."""
    params = torch.tensor([100.0, 100.0, 99.5, 99.5], dtype=F64)
    cam = ot.Camera("equidistant", params, (200, 200), fov=math.radians(150),
                    blind_fov=math.radians(40))
    _, valid = cam.ray_grid()
    v, u = torch.meshgrid(torch.arange(200, dtype=F64), torch.arange(200, dtype=F64),
                          indexing="ij")
    r = torch.hypot(u - 99.5, v - 99.5)
    expected = (r > 100 * math.radians(20) + 1e-9) & (r <= 100 * math.radians(75) + 1e-9)
    assert torch.equal(valid, expected)
    assert "blind_fov=40.0 deg" in repr(cam)
    with pytest.raises(ValueError, match="blind_fov: must be smaller than fov"):
        ot.Camera("equidistant", params, (200, 200), fov=1.0, blind_fov=1.5)


def test_cameras_pickle_for_dataloader_workers():
    """A Camera crosses process boundaries (DataLoader workers): models pickle by name."""
    import pickle
    for name, cases in CASES.items():
        cam = ot.Camera(name, torch.tensor(cases[0][0], dtype=F64), cases[0][1])
        back = pickle.loads(pickle.dumps(cam))
        assert back.model is cam.model and torch.equal(back.params, cam.params)
        pts = fibonacci_sphere(50)
        assert torch.equal(back.project(pts)[0], cam.project(pts)[0])


def test_smallest_positive_root_against_numpy_roots():
    """The fold finder (``cameras._base.smallest_positive_root``) against numpy's own roots, on a
    batch mixing polynomials with positive roots, without any, and constant ones (higher
    coefficients all zero, an undistorted lens: inf, alone or in the batch)."""
    import numpy as np

    from omniscape_torch.cameras._base import smallest_positive_root

    gen = torch.Generator().manual_seed(0)
    coeffs = torch.cat((torch.ones(64, 1, dtype=F64),
                        torch.randn(64, 3, generator=gen, dtype=F64)), -1)
    coeffs[::4, 1:] = 0.0          # constants
    coeffs[1::4, 2:] = 0.0         # linear: a root where c1 < 0
    got = smallest_positive_root(coeffs)
    for row, value in zip(coeffs.numpy(), got.tolist()):
        roots = np.roots(np.trim_zeros(row[::-1], "f"))   # highest power first
        positive = [r.real for r in roots if abs(r.imag) <= 1e-7 * abs(r) and r.real > 0]
        want = min(positive) if positive else math.inf
        assert value == pytest.approx(want, rel=1e-9)
    constant = torch.tensor([[2.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=F64)
    assert torch.equal(smallest_positive_root(constant), torch.full((2,), math.inf, dtype=F64))


@pytest.mark.parametrize("name", ["opencv", "thin_prism_fisheye", "fisheye624"])
def test_written_out_distortion_jacobians_are_the_complex_step(name):
    """The 2 x 2 Jacobians the 2-D Newton inverses use, written out per model, against the
    complex step of the distortion itself (``cameras._base._complex_step``, exact to rounding)."""
    from omniscape_torch.cameras import _base, fisheye, perspective
    distort, jacobian = {
        "opencv": (perspective._opencv_distort, perspective._opencv_jacobian),
        "thin_prism_fisheye": (fisheye._tpf_distort, fisheye._tpf_jacobian),
        "fisheye624": (fisheye._f624_distort, fisheye._f624_jacobian)}[name]
    gen = torch.Generator().manual_seed(0)
    c = 0.05 * torch.randn(len(ot.cameras.get_model(name).param_names) - 4, generator=gen,
                           dtype=F64)
    mx, my = (torch.rand(200, generator=gen, dtype=F64) * 2 - 1 for _ in range(2))
    want = _base._complex_step(distort, mx, my, c)
    got = jacobian(mx, my, c)
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("name", ["fov", "division", "opencv", "thin_prism_fisheye",
                                  "fisheye624"])
def test_ray_grid_and_field_of_view_of_the_new_models(name):
    """``Camera.ray_grid`` and ``field_of_view`` from the models' ``max_angle``: every pixel
    of the first case valid, its rays within the limit, and the fisheyes seeing past 180
    degrees through ``atan2``."""
    params, size = CASES[name][0]
    p = torch.tensor(params, dtype=F64)
    # the same lens on a sensor 8 times coarser (pixel centres at integers: c' = (c + 0.5) / 8
    # - 0.5): the iterative inverses take ~3 s for a 1280 x 960 grid on a loaded machine
    p[:2], p[2:4] = p[:2] / 8, (p[2:4] + 0.5) / 8 - 0.5
    cam = ot.Camera(name, p, (size[0] // 8, size[1] // 8))
    rays, valid = cam.ray_grid()
    assert bool(valid.all())
    limit = float(cam.model.max_angle(cam.params))
    assert float(theta_of(rays).max()) < limit
    fov = float(cam.field_of_view())
    assert 0 < fov <= 2 * limit
    if name in ("thin_prism_fisheye", "fisheye624"):
        assert fov > math.pi
