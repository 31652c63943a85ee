"""Independent reference implementation of Scaramuzza's OCamCalib camera model.

Pure-Python/numpy, statement-for-statement transcription of the *published*
OCamCalib sources -- deliberately NOT derived from ``omniscape_torch`` -- so
that tests can check our library against the toolbox's own formulas.

Transcribed from
----------------
* C functions ``get_ocam_model``, ``cam2world``, ``world2cam`` of
  ``ocam_functions.cpp`` / ``ocam_functions.h`` ("Copyright (C) 2008 DAVIDE
  SCARAMUZZA, ETH Zurich; Author: Davide Scaramuzza"), the C example code
  shipped with the OCamCalib toolbox, as copied verbatim in
  github.com/mhirano/OCamCalib_undistortFunctions
  (ocam_functions.cpp / ocam_functions.h, commit
  1afdcd1d8ff85f4868945b97e75c895912ba0007).  Cross-checked: the three
  functions are identical in github.com/evroon/undistort-functions
  (ocam_functions.cpp, commit 13041c3a94331706acbe9364d732911dd83e28cd).
* MATLAB ``findinvpoly`` / ``findinvpoly2`` / ``invFUN`` of the OCamCalib
  toolbox ("Copyright (C) 2008 DAVIDE SCARAMUZZA, ETH Zurich"), the
  original variant with ``theta = [-pi/2:0.01:1.20]`` and the
  ``while maxerr > 0.01`` degree search, as reproduced in
  github.com/valgur/ocam (ocam/findinvpoly.py, a SMOP translation that keeps
  the MATLAB text, commit 3f329006d32108fcb4cfde92d60fcf6e9b57738b).
  Other published copies differ: github.com/urbste/ImprovedOcamCalib
  (OcamCalibUrban/Scaramuzza_OCamCalib_v3.0_win/Scaramuzza_OCamCalib_v3.0_win/
  findinvpoly.m, commit 7d9ed056b0fd9b423f677ad8f89101764adb662b) samples
  ``theta = -pi/2+0.01:0.01:1.4``; github.com/taoihsu/myMatlab2Cpp
  (findinvpoly.m) keeps ``[-pi/2:0.01:1.20]`` but forces N = length(ss)-1.
  ``theta_start``/``theta_stop`` below allow the v3.0 sampling too.
* The radius passed to findinvpoly by the toolbox (export_data.m,
  undistort.m, e.g. github.com/nxp-imx/OCamCalib export_data.m, commit
  556abf324e8681fe40c26e037e060113237fe0f7) is
  ``sqrt((width/2)^2 + (height/2)^2)``; export_data.m writes ``ss`` in
  ascending order with ``%e`` and ``invpol`` reversed (ascending) with ``%f``.

OCamCalib frame (kept as is here)
---------------------------------
point2D[0] is the ROW and point2D[1] the COLUMN (0-based, C convention);
xc is the row of the centre, yc its column; 3D x runs along rows, y along
columns, z = pol(rho).  With the usual negative pol[0] the scene lies at -z.
``theta`` in world2cam/findinvpoly is the *elevation* atan(z / sqrt(x^2+y^2)),
so the optical axis (-z) is theta = -pi/2.
"""

from __future__ import annotations

import math
import re

import numpy as np

CMV_MAX_BUF = 1024  # ocam_functions.h
MAX_POL_LENGTH = 64  # ocam_functions.h


# ---------------------------------------------------------------------------
# get_ocam_model: emulation of the C stdio calls it makes, in the same order
# ---------------------------------------------------------------------------
_WS = " \t\n\v\f\r"  # isspace() in the C locale
_INT_RE = re.compile(r"[+-]?[0-9]+")
_DBL_RE = re.compile(
    r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
    r"|inf(?:inity)?|nan(?:\([0-9A-Za-z_]*\))?)",
    re.IGNORECASE,
)


class _CFile:
    """Just enough of fgets/fscanf on a text stream to replay get_ocam_model."""

    def __init__(self, text: str):
        self.s = text
        self.pos = 0

    def fgets(self, n: int) -> str:
        # reads at most n-1 characters, stopping after a newline
        end = self.s.find("\n", self.pos, self.pos + n - 1)
        end = (self.pos + n - 1) if end < 0 else end + 1
        out = self.s[self.pos : end]
        self.pos = min(end, len(self.s))
        return out

    def skip_ws(self) -> None:
        # a whitespace directive ("\n", " ") in a scanf format matches any
        # amount of whitespace, including none
        while self.pos < len(self.s) and self.s[self.pos] in _WS:
            self.pos += 1

    def _scan(self, regex, conv, what):
        self.skip_ws()  # %d and %lf skip leading whitespace
        m = regex.match(self.s, self.pos)
        if m is None:
            raise ValueError(
                f"fscanf {what} failed at offset {self.pos}: {self.s[self.pos:self.pos + 30]!r}"
            )
        self.pos = m.end()
        return conv(m.group(0))

    def scan_int(self) -> int:  # "%d"
        return self._scan(_INT_RE, int, "%d")

    def scan_double(self) -> float:  # "%lf"
        return self._scan(_DBL_RE, float, "%lf")


def read_ocam_model(path) -> dict:
    """Transcription of C ``get_ocam_model(struct ocam_model*, char *filename)``.

    Returns dict(pol, invpol, xc, yc, c, d, e, width, height); pol and invpol
    are float64 arrays in the file's (ascending) order.  Where the C code
    would silently leave fields uninitialised (a failed fscanf) this raises
    ValueError instead.
    """
    with open(path, "r", newline="") as fh:  # keep "\r" like fopen(.., "r") on POSIX
        f = _CFile(fh.read())

    # Read polynomial coefficients
    f.fgets(CMV_MAX_BUF)
    f.skip_ws()  # fscanf(f,"\n");
    length_pol = f.scan_int()  # fscanf(f,"%d", length_pol);
    if not 0 <= length_pol <= MAX_POL_LENGTH:
        raise ValueError(f"length_pol={length_pol} outside [0, {MAX_POL_LENGTH}]")
    pol = []
    for i in range(length_pol):
        pol.append(f.scan_double())  # fscanf(f," %lf",&pol[i]);

    # Read inverse polynomial coefficients
    f.skip_ws()  # fscanf(f,"\n");
    f.fgets(CMV_MAX_BUF)
    f.skip_ws()  # fscanf(f,"\n");
    length_invpol = f.scan_int()
    if not 0 <= length_invpol <= MAX_POL_LENGTH:
        raise ValueError(f"length_invpol={length_invpol} outside [0, {MAX_POL_LENGTH}]")
    invpol = []
    for i in range(length_invpol):
        invpol.append(f.scan_double())

    # Read center coordinates
    f.skip_ws()  # fscanf(f,"\n");
    f.fgets(CMV_MAX_BUF)
    f.skip_ws()  # fscanf(f,"\n");
    xc = f.scan_double()  # fscanf(f,"%lf %lf\n", xc, yc);
    f.skip_ws()
    yc = f.scan_double()
    f.skip_ws()

    # Read affine coefficients
    f.fgets(CMV_MAX_BUF)
    f.skip_ws()  # fscanf(f,"\n");
    c = f.scan_double()  # fscanf(f,"%lf %lf %lf\n", c,d,e);
    f.skip_ws()
    d = f.scan_double()
    f.skip_ws()
    e = f.scan_double()
    f.skip_ws()

    # Read image size
    f.fgets(CMV_MAX_BUF)
    f.skip_ws()  # fscanf(f,"\n");
    height = f.scan_int()  # fscanf(f,"%d %d", height, width);
    f.skip_ws()
    width = f.scan_int()

    return dict(
        pol=np.asarray(pol, dtype=np.float64),
        invpol=np.asarray(invpol, dtype=np.float64),
        xc=xc,
        yc=yc,
        c=c,
        d=d,
        e=e,
        width=width,
        height=height,
    )


# ---------------------------------------------------------------------------
# cam2world / world2cam: one point at a time, exactly the C statements
# ---------------------------------------------------------------------------
def _c_div(a: float, b: float) -> float:
    """IEEE-754 double division as C does it (x/0 -> +-inf or nan, no exception)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.float64(a) / np.float64(b))


def cam2world_point(point2D, model) -> list:
    """C ``cam2world(double point3D[3], double point2D[2], struct ocam_model*)``."""
    pol = [float(v) for v in model["pol"]]
    xc = float(model["xc"])
    yc = float(model["yc"])
    c = float(model["c"])
    d = float(model["d"])
    e = float(model["e"])
    length_pol = len(pol)
    invdet = _c_div(1.0, c - d * e)  # 1/det(A), where A = [c,d;e,1] as in the Matlab file

    p0 = float(point2D[0])
    p1 = float(point2D[1])
    xp = invdet * ((p0 - xc) - d * (p1 - yc))
    yp = invdet * (-e * (p0 - xc) + c * (p1 - yc))

    r = math.sqrt(xp * xp + yp * yp)  # distance [pixels] of the point from the image center
    zp = pol[0]
    r_i = 1.0
    for i in range(1, length_pol):
        r_i *= r
        zp += r_i * pol[i]

    # normalize to unit norm
    invnorm = _c_div(1.0, math.sqrt(xp * xp + yp * yp + zp * zp))

    point3D = [0.0, 0.0, 0.0]
    point3D[0] = invnorm * xp
    point3D[1] = invnorm * yp
    point3D[2] = invnorm * zp
    return point3D


def world2cam_point(point3D, model) -> list:
    """C ``world2cam(double point2D[2], double point3D[3], struct ocam_model*)``."""
    invpol = [float(v) for v in model["invpol"]]
    xc = float(model["xc"])
    yc = float(model["yc"])
    c = float(model["c"])
    d = float(model["d"])
    e = float(model["e"])
    length_invpol = len(invpol)
    P0, P1, P2 = float(point3D[0]), float(point3D[1]), float(point3D[2])
    norm = math.sqrt(P0 * P0 + P1 * P1)
    theta = math.atan(_c_div(P2, norm))  # computed before the branch, as in C

    point2D = [0.0, 0.0]
    if norm != 0:
        invnorm = 1.0 / norm
        t = theta
        rho = invpol[0]
        t_i = 1.0

        for i in range(1, length_invpol):
            t_i *= t
            rho += t_i * invpol[i]

        x = P0 * invnorm * rho
        y = P1 * invnorm * rho

        point2D[0] = x * c + y * d + xc
        point2D[1] = x * e + y + yc
    else:
        point2D[0] = xc
        point2D[1] = yc
    return point2D


def cam2world(point2D_rowcol, model) -> np.ndarray:
    """cam2world for an array of shape (..., 2) (row, col) -> (..., 3) unit vectors."""
    p = np.asarray(point2D_rowcol, dtype=np.float64)
    flat = p.reshape(-1, 2)
    out = np.array([cam2world_point(q, model) for q in flat], dtype=np.float64)
    return out.reshape(p.shape[:-1] + (3,))


def world2cam(point3D, model) -> np.ndarray:
    """world2cam for an array of shape (..., 3) -> (..., 2) (row, col) pixels."""
    P = np.asarray(point3D, dtype=np.float64)
    flat = P.reshape(-1, 3)
    out = np.array([world2cam_point(q, model) for q in flat], dtype=np.float64)
    return out.reshape(P.shape[:-1] + (2,))


# ---------------------------------------------------------------------------
# findinvpoly (MATLAB toolbox)
# ---------------------------------------------------------------------------
def matlab_colon(a: float, step: float, b: float) -> np.ndarray:
    """``a:step:b`` (count as MATLAB's colon: floor((b-a)/step) + 1 elements)."""
    n = int(math.floor((b - a) / step + 1e-10))
    return a + step * np.arange(n + 1, dtype=np.float64)


def invFUN(ss, theta, radius) -> np.ndarray:
    """MATLAB ``r = invFUN(ss, theta, radius)``: exact inverse of ss per angle.

    For each elevation theta solves ss(rho) = tan(theta)*rho with ``roots`` and
    keeps the unique real root in (0, radius); inf when none or several.
    """
    theta = np.atleast_1d(np.asarray(theta, dtype=np.float64))
    m = np.tan(theta)

    r = np.empty(len(m), dtype=np.float64)
    poly_coef = np.asarray(ss, dtype=np.float64)[::-1].copy()  # ss(end:-1:1)
    poly_coef_tmp = poly_coef.copy()
    for j in range(len(m)):
        poly_coef_tmp[-2] = poly_coef[-2] - m[j]  # poly_coef_tmp(end-1)=poly_coef(end-1)-m(j);
        rhoTmp = np.roots(poly_coef_tmp)
        # MATLAB's > and < on complex values compare the real parts
        res = rhoTmp[(np.imag(rhoTmp) == 0) & (np.real(rhoTmp) > 0) & (np.real(rhoTmp) < radius)]
        if res.size == 0 or res.size > 1:
            r[j] = np.inf
        else:
            r[j] = np.real(res[0])
    return r


def findinvpoly2(ss, radius, N, theta_start=-math.pi / 2, theta_stop=1.20):
    """MATLAB ``[pol, err, N] = findinvpoly2(ss, radius, N)`` (pol descending, MATLAB order)."""
    theta = matlab_colon(theta_start, 0.01, theta_stop)  # theta = [-pi/2:0.01:1.20];
    r = invFUN(ss, theta, radius)
    ind = np.nonzero(r != np.inf)[0]
    theta = theta[ind]
    r = r[ind]

    pol = np.polyfit(theta, r, N)
    err = np.abs(r - np.polyval(pol, theta))  # approximation error in pixels
    return pol, err, N


def findinvpoly(pol, radius, max_error=0.01, N=None, theta_start=-math.pi / 2, theta_stop=1.20):
    """MATLAB ``[pol, err, N] = findinvpoly(ss, radius[, N])``.

    ``pol`` is the direct polynomial (ocam_model.ss, ascending, as in the
    calib file).  Without N the degree is increased from 2 until the max
    fitting error is <= max_error (0.01 px in the toolbox).

    Returns ``(invpol, err, N)``: invpol in the ascending order the C
    world2cam uses (length N+1, i.e. what export_data.m writes), err the
    per-sample |r - polyval| in pixels, N the degree.
    """
    ss = pol
    if N is None:
        maxerr = np.inf
        N = 1
        while maxerr > max_error:  # Repeat until the reprojection error is smaller than 0.01 pixels
            N = N + 1
            p, err, _ = findinvpoly2(ss, radius, N, theta_start, theta_stop)
            maxerr = np.max(err)
    else:
        p, err, N = findinvpoly2(ss, radius, N, theta_start, theta_stop)
    return p[::-1].copy(), err, N


def toolbox_radius(width, height) -> float:
    """Radius the toolbox passes to findinvpoly (export_data.m / undistort.m)."""
    return math.sqrt((width / 2) ** 2 + (height / 2) ** 2)
