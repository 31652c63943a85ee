"""Readers of other tools' camera files (issue 34, part 3): ``Camera.load``, ``ot.cameras.load_all``
and ``omniscape-torch info --camera``.

Three kinds of evidence: every file ``write_camera`` writes reads back as the same camera,
bit for bit (one documented exception: basalt's ``ucm`` alpha form, a division each way); real
files written by each tool (``tests/data/camera_files/README.md``) read as the values they hold;
and where a reference exists, the camera read projects as the tool does (cv2.projectPoints,
pycolmap, the reference pixels of Aria_data_tools' own test). A malformed file is one
``ValueError`` line naming the file and the line or key.
"""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
import torch

import omniscape_torch as ot
from omniscape_torch import cli
from omniscape_torch.cameras import FORMATS, READ_FORMATS, load_all
from omniscape_torch.cameras.export import supported_models
from omniscape_torch.cameras.readers import detect_format

from conftest import OCAMCALIB_FILE, ROOT

FILES = ROOT / "tests" / "data" / "camera_files"
D = torch.float64
SIZE = (480, 640)

#: One camera per model that some format holds, valid for every format that holds it (Kalibr:
#: principal point >= 0, alpha < 1; the Kannala-Brandt formats: below 90 degrees off the axis).
PARAMS = {
    "pinhole": [400.0, 401.0, 319.5, 239.5],
    "kannala_brandt": [300.1, 300.3, 320.25, 240.125, 0.01, -0.005, 0.001, 0.0003],
    "unified": [280.0, 285.0, 319.5, 239.5, 0.9, -0.05, 0.01, 0.001, -0.002],
    "double_sphere": [160.0, 161.0, 319.5, 239.5, -0.2, 0.6],
    "eucm": [220.0, 221.0, 320.5, 238.5, 0.6, 1.1],
    "fov": [300.0, 301.0, 319.5, 239.5, 0.9],
    "division": [300.0, 301.0, 319.5, 239.5, -1e-6],
    "opencv": [400.0, 401.0, 319.5, 239.5, -0.1, 0.01, 0.001, -0.002, 0.001, 0.0, 0.0, 0.0,
               0.0, 0.0, 0.0, 0.0],
    "thin_prism_fisheye": [300.0, 301.0, 319.5, 239.5, 0.01, -0.005, 0.001, -0.001, 0.0, 0.0,
                           0.0005, -0.0005],
    "fisheye624": [300.0, 301.0, 319.5, 239.5, 0.01, -0.005, 0.001, 0.0, 0.0, 0.0, 0.0005,
                   -0.0005, 0.0001, 0.0, -0.0001, 0.0],
}
#: basalt holds the unified model without distortion only.
UCM = [280.0, 285.0, 319.5, 239.5, 0.9, 0.0, 0.0, 0.0, 0.0]
#: Kalibr's pinhole-radtan holds k1, k2, p1, p2 of the opencv model only.
RADTAN = [400.0, 401.0, 319.5, 239.5, -0.1, 0.01, 0.001, -0.002] + [0.0] * 8
#: The longer coefficient vectors: COLMAP's FULL_OPENCV (k1..k6), OpenCV's 8 and 12.
OPENCV_LONG = {
    "colmap": [400.0, 401.0, 319.5, 239.5, -0.1, 0.01, 0.001, -0.002, 0.001, 0.02, -0.003,
               0.0004] + [0.0] * 4,
    "opencv": [400.0, 401.0, 319.5, 239.5, -0.1, 0.01, 0.001, -0.002, 0.001, 0.02, -0.003,
               0.0004, 0.0005, -0.0001, 0.0002, 0.0001],
}


def _scaramuzza() -> ot.Camera:
    return ot.Camera.from_ocamcalib(OCAMCALIB_FILE)


def _camera(fmt: str, model: str) -> ot.Camera:
    if model == "scaramuzza":
        return _scaramuzza()
    if model == "opencv-long":
        model, params = "opencv", OPENCV_LONG[fmt]
    else:
        params = {("basalt", "unified"): UCM, ("kalibr", "opencv"): RADTAN}.get((fmt, model),
                                                                               PARAMS[model])
    return ot.Camera(model, torch.tensor(params, dtype=D), SIZE)


def _round_trip_cases():
    cases = []
    for fmt in FORMATS:
        models = supported_models(fmt)
        if fmt == "json":   # every model: one per family is enough for the JSON itself
            models = ("pinhole", "kannala_brandt", "unified", "scaramuzza")
        cases += [pytest.param(fmt, m, id=f"{fmt}-{m}") for m in models]
    cases += [pytest.param(fmt, "opencv-long", id=f"{fmt}-opencv-long") for fmt in OPENCV_LONG]
    return cases


# --------------------------------------------------------------------------------------------
# save then load
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt,model", _round_trip_cases())
def test_save_then_load_gives_the_same_camera(tmp_path, fmt, model):
    camera = _camera(fmt, model)
    name = {"colmap": "cameras.txt", "ocamcalib": "calib_results.txt", "basalt": "calib.json",
            "json": "camera.json"}.get(fmt, "camera.yaml")
    path = camera.save(tmp_path / name, fmt)
    assert detect_format(path) == fmt
    back = ot.Camera.load(path)
    assert back.model.name == camera.model.name
    assert back.image_size == camera.image_size
    assert back.params.dtype == D
    if (fmt, model) == ("basalt", "unified"):
        # basalt's ucm is the alpha form: fx / (1 + xi) written, fx' / (1 - alpha) read back.
        torch.testing.assert_close(back.params, camera.params, rtol=4e-16, atol=0)
    else:
        assert back.params.tolist() == camera.params.tolist()
    assert ot.Camera.load(path, fmt).params.tolist() == back.params.tolist()


def test_every_format_written_is_read():
    assert set(FORMATS) <= set(READ_FORMATS)


def test_the_opencv_skew_round_trips(tmp_path):
    for model in ("kannala_brandt", "unified"):
        camera = ot.Camera(model, torch.tensor(PARAMS[model] + [0.25], dtype=D), SIZE)
        back = ot.Camera.load(camera.save(tmp_path / f"{model}.yaml", "opencv"))
        assert back.param_names[-1] == "s"
        assert back.params.tolist() == camera.params.tolist()


def test_an_accepted_fov_is_read_back_as_the_fov(tmp_path):
    camera = ot.Camera("kannala_brandt", torch.tensor([150.0, 150.0, 319.5, 239.5, 0, 0, 0, 0],
                                                      dtype=D), SIZE)
    with pytest.warns(UserWarning):
        path = camera.save(tmp_path / "wide.yaml", "kalibr", accept_fov=True)
    back = ot.Camera.load(path)
    assert back.fov == pytest.approx(math.pi)
    assert ot.Camera.load(path, fov=2.0).fov == 2.0


# --------------------------------------------------------------------------------------------
# Real files
# --------------------------------------------------------------------------------------------

def test_kalibr_real_files():
    cam = ot.Camera.load(FILES / "kalibr" / "camchain-camera.yaml")
    assert cam.model.name == "kannala_brandt" and cam.image_size == (480, 640)
    assert cam.params.tolist() == [277.95596230891084, 278.4167467580337, 315.5269754313737,
                                   244.46893770533453, -0.005908650672531068,
                                   0.01587953759563821, -0.024196671184075886,
                                   0.015501252412920248]
    cams = load_all(FILES / "kalibr" / "chain-omni-radtan.yaml")
    assert list(cams) == ["cam0", "cam1"]
    cam1 = ot.Camera.load(FILES / "kalibr" / "chain-omni-radtan.yaml", name="cam1")
    assert cam1.model.name == "unified" and cam1.image_size == (480, 752)
    # Kalibr's omni intrinsics are [xi, fu, fv, pu, pv]; ours fx, fy, cx, cy, xi, k1, k2, p1, p2
    assert cam1.params.tolist() == [805.0992800974523, 805.1201800399643, 376.61967341034676,
                                    256.0786828765575, 0.7476616047651173,
                                    -0.34330808866302887, 0.14844603008818044,
                                    -0.0003074632859414297, 0.0013186394350600886]
    assert cams["cam1"].params.tolist() == cam1.params.tolist()


def test_kalibr_omni_matches_cv2_omnidir():
    cv2 = pytest.importorskip("cv2")
    if not hasattr(cv2, "omnidir"):
        pytest.skip("OpenCV without the contrib omnidir module")
    cam = ot.Camera.load(FILES / "kalibr" / "chain-omni-radtan.yaml")
    K, Dist, xi = cam.to_opencv_omnidir()
    points = np.array([[[x, y, 1.0]] for x in (-0.6, 0.0, 0.4) for y in (-0.3, 0.2)])
    ref, _ = cv2.omnidir.projectPoints(points, np.zeros(3), np.zeros(3), K, float(xi[0]), Dist)
    ours, valid = cam.project(torch.from_numpy(points[:, 0]))
    assert bool(valid.all())
    np.testing.assert_allclose(ours.numpy(), ref[:, 0], atol=1e-6)


def test_basalt_real_files():
    cams = load_all(FILES / "basalt" / "t265_kb4_calib.json")
    assert list(cams) == ["cam0", "cam1"]
    assert cams["cam1"].model.name == "kannala_brandt" and cams["cam1"].image_size == (800, 848)
    assert cams["cam1"].params.tolist()[:4] == [286.94962264945976, 286.69078453656996,
                                                431.3293011565108, 390.0750907521924]
    ds = ot.Camera.load(FILES / "basalt" / "euroc_ds_calib.json", name="cam0")
    assert ds.model.name == "double_sphere"
    assert ds.params.tolist() == [349.7560023050409, 348.72454229977037, 365.89440762590149,
                                  249.32995565708704, -0.2409573942178872, 0.566996899163044]


def test_orbslam3_real_files():
    stereo = load_all(FILES / "orbslam3" / "TUM-VI-stereo.yaml")
    assert list(stereo) == ["Camera1", "Camera2"]
    assert all(c.model.name == "kannala_brandt" and c.image_size == (512, 512)
               for c in stereo.values())
    assert stereo["Camera2"].params.tolist() == [
        190.44236969414825, 190.4344384721956, 252.59949716835982, 254.91723064636983,
        0.0034003170790442797, 0.001766278153469831, -0.00266312569781606,
        0.0003299517423931039]
    mono = ot.Camera.load(FILES / "orbslam3" / "EuRoC-mono.yaml")
    assert mono.model.name == "opencv" and mono.image_size == (480, 752)
    assert mono.params.tolist()[:8] == [458.654, 457.296, 367.215, 248.375, -0.28340811,
                                        0.07395907, 0.00019359, 1.76187114e-05]


def test_orbslam3_older_format(tmp_path):
    """ORB-SLAM2 / early ORB-SLAM3 settings: Camera.fx ..., no File.version, no size."""
    path = tmp_path / "TUM1.yaml"
    path.write_text("%YAML:1.0\nCamera.fx: 517.306408\nCamera.fy: 516.469215\n"
                    "Camera.cx: 318.643040\nCamera.cy: 255.313989\nCamera.k1: 0.0\n"
                    "Camera.k2: 0.0\nCamera.p1: 0.0\nCamera.p2: 0.0\nCamera.fps: 30.0\n")
    with pytest.raises(ValueError, match="no image size; pass image_size"):
        ot.Camera.load(path)
    cam = ot.Camera.load(path, image_size=(480, 640))
    assert cam.model.name == "pinhole" and list(load_all(path, image_size=(480, 640))) == ["Camera"]


@pytest.mark.parametrize("name", ["left_intrinsics.yml", "tutorial_camera_charuco.yml"])
def test_opencv_real_files_project_as_cv2(name):
    cv2 = pytest.importorskip("cv2")
    cam = ot.Camera.load(FILES / "opencv" / name)
    assert cam.model.name == "opencv" and cam.image_size == (480, 640)
    fs = cv2.FileStorage(str(FILES / "opencv" / name), cv2.FILE_STORAGE_READ)
    K, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
    fs.release()
    points = np.array([[x, y, 1.0] for x in (-0.5, -0.1, 0.3) for y in (-0.3, 0.0, 0.35)])
    ref, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, dist)
    ours, valid = cam.project(torch.from_numpy(points))
    compared = int(valid.sum())
    assert compared > 0
    np.testing.assert_allclose(ours[valid].numpy(), ref[:, 0][valid.numpy()], atol=1e-6)


def test_ros_camera_info_yaml(tmp_path):
    """ROS's camera_calibration writes untagged {rows, cols, data} matrices and names the
    distortion model (plumb_bob, rational_polynomial, equidistant)."""
    text = ("image_width: 800\nimage_height: 600\ncamera_name: cam\ncamera_matrix:\n"
            "  rows: 3\n  cols: 3\n  data: [540.5, 0, 401.25, 0, 541.5, 299.75, 0, 0, 1]\n"
            "distortion_model: {model}\ndistortion_coefficients:\n  rows: 1\n  cols: {n}\n"
            "  data: [{coeffs}]\n")
    path = tmp_path / "ost.yaml"
    path.write_text(text.format(model="plumb_bob", n=5,
                                coeffs="-0.3125, 0.0825, 0.0025, -0.00015, 0"))
    cam = ot.Camera.load(path)
    assert cam.model.name == "opencv" and cam.image_size == (600, 800)
    assert cam.params.tolist()[:9] == [540.5, 541.5, 401.25, 299.75, -0.3125, 0.0825,
                                       0.0025, -0.00015, 0.0]
    path.write_text(text.format(model="equidistant", n=4, coeffs="0.01, -0.002, 0.0003, 0"))
    fisheye = ot.Camera.load(path)
    assert fisheye.model.name == "kannala_brandt"
    assert fisheye.params.tolist()[4:] == [0.01, -0.002, 0.0003, 0.0]


def _colmap_binary(tmp_path, text_path):
    """cameras.bin of the same cameras, written by pycolmap."""
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction()
    for line in text_path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            t = line.split()
            cam = pycolmap.Camera(model=t[1], width=int(t[2]), height=int(t[3]),
                                  params=[float(v) for v in t[4:]], camera_id=int(t[0]))
            rec.add_camera(cam)
    folder = tmp_path / "sparse"
    folder.mkdir()
    rec.write_binary(str(folder))
    return pycolmap, folder


@pytest.mark.parametrize("name", ["fisheye-cameras.txt", "format-example-cameras.txt"])
def test_colmap_real_files_text_binary_and_pycolmap_agree(tmp_path, name):
    text = load_all(FILES / "colmap" / name)
    pycolmap, folder = _colmap_binary(tmp_path, FILES / "colmap" / name)
    binary = load_all(folder / "cameras.bin")
    assert detect_format(folder / "cameras.bin") == "colmap"
    from_folder = load_all(folder)
    assert detect_format(folder) == "colmap"
    rec = pycolmap.Reconstruction(str(folder))
    from_rec = load_all(rec)
    from_cam = {k: ot.Camera.load(c) for k, c in ((str(i), c) for i, c in rec.cameras.items())}
    for cams in (binary, from_folder, from_rec, from_cam):
        assert sorted(cams) == sorted(text)   # pycolmap writes its cameras in its own order
        for key in text:
            assert cams[key].params.tolist() == text[key].params.tolist()
            assert cams[key].image_size == text[key].image_size
    # pycolmap projects to (ours + 0.5): its top-left pixel centre is (0.5, 0.5)
    points = np.array([[x, y, 1.0] for x in (-0.4, 0.0, 0.3) for y in (-0.2, 0.25)])
    for cid, ref_cam in rec.cameras.items():
        ours, valid = text[str(cid)].project(torch.from_numpy(points))
        ref = np.asarray(ref_cam.img_from_cam(points))
        assert bool(valid.any())
        np.testing.assert_allclose(ours[valid].numpy() + 0.5, ref[valid.numpy()], atol=1e-6)


def test_colmap_documentation_example():
    cams = load_all(FILES / "colmap" / "format-example-cameras.txt")
    assert list(cams) == ["1", "2", "3"]
    assert [c.model.name for c in cams.values()] == ["pinhole", "pinhole", "opencv"]
    assert cams["1"].params.tolist() == [2559.81, 2559.81, 1535.5, 1151.5]
    assert cams["3"].params.tolist()[:5] == [2559.69, 2559.69, 1535.5, 1151.5, -0.0218531]
    assert all(c.image_size == (2304, 3072) for c in cams.values())


def test_colmap_real_file_values():
    cam = ot.Camera.load(FILES / "colmap" / "fisheye-cameras.txt", name="2")
    assert cam.model.name == "kannala_brandt" and cam.image_size == (3264, 3264)
    assert cam.params.tolist()[:4] == [991.0, 991.0, 1611.5, 1616.5]   # cx, cy - 0.5


def test_aria_fixture_projects_as_aria_data_tools():
    """The reference pixels of Aria_data_tools' DeviceModelTests.cpp, for its own JSON."""
    cams = load_all(FILES / "aria" / "DeviceModelTests-calib.json")
    assert list(cams) == ["camera-slam-left", "camera-et-left"]
    slam, et = cams["camera-slam-left"], cams["camera-et-left"]
    assert slam.model.name == "fisheye624" and slam.image_size == (480, 640)
    assert et.model.name == "kannala_brandt" and et.image_size == (480, 640)
    uv, _ = slam.model.project(torch.tensor([2.0, 3.0, 1.0], dtype=D), slam.params)
    np.testing.assert_allclose(uv.numpy(), [493.09928578162271, 499.64892867243407], atol=1e-6)
    uv, _ = et.model.project(torch.tensor([-1.0, -2.0, 1.0], dtype=D), et.params)
    np.testing.assert_allclose(uv.numpy(), [36.044133853218739, -327.91173229356252], atol=1e-6)


def test_aria_sizes_labels_and_fisheye624_params(tmp_path):
    params = [600.5, 1407.25, 1408.5] + [0.1 * i for i in range(1, 13)]
    path = tmp_path / "calibration.json"
    path.write_text(f'{{"CameraCalibrations": [{{"Label": "camera-rgb", "Projection": '
                    f'{{"Name": "FisheyeRadTanThinPrism", "Params": {params}}}}}, '
                    f'{{"Label": "camera-new", "ImageSize": [1408, 1408], "Projection": '
                    f'{{"Name": "FisheyeRadTanThinPrism", "Params": {params}}}}}]}}')
    rgb = ot.Camera.load(path)
    assert rgb.image_size == (2880, 2880)   # projectaria_tools' full-resolution RGB
    assert rgb.params.tolist() == [600.5] + params   # one focal: fx = fy
    assert ot.Camera.load(path, name="camera-new").image_size == (1408, 1408)


def test_aria_mps_online_calibration_jsonl(tmp_path):
    """MPS writes one JSON record per line, with ImageSizes beside CameraCalibrations."""
    record = ('{"tracking_timestamp_us": 1, "ImageSizes": [[640, 480], [1408, 1408]], '
              '"CameraCalibrations": [{"Label": "camera-slam-left", "Projection": {"Name": '
              '"FisheyeRadTanThinPrism", "Params": [240, 320, 240, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, '
              '0, 0]}}, {"Label": "camera-rgb", "Projection": {"Name": "FisheyeRadTanThinPrism", '
              '"Params": [600, 704, 704, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]}}]}')
    path = tmp_path / "online_calibration.jsonl"
    path.write_text(record + "\n" + record.replace('"tracking_timestamp_us": 1', '"tracking_'
                                                      'timestamp_us": 2') + "\n")
    cams = load_all(path)
    assert detect_format(path) == "aria"
    assert cams["camera-rgb"].image_size == (1408, 1408)   # ImageSizes, not the 2880 default
    assert cams["camera-slam-left"].image_size == (480, 640)


@pytest.mark.parametrize("path,fmt", [
    ("kalibr/camchain-camera.yaml", "kalibr"), ("basalt/euroc_ds_calib.json", "basalt"),
    ("orbslam3/EuRoC-mono.yaml", "orbslam3"), ("opencv/left_intrinsics.yml", "opencv"),
    ("colmap/fisheye-cameras.txt", "colmap"), ("aria/DeviceModelTests-calib.json", "aria"),
])
def test_real_files_are_recognised(path, fmt):
    assert detect_format(FILES / path) == fmt
    assert detect_format(OCAMCALIB_FILE) == "ocamcalib"


# --------------------------------------------------------------------------------------------
# Malformed files: one line, the file, the line or key, what was expected
# --------------------------------------------------------------------------------------------

KALIBR = ("cam0:\n  camera_model: pinhole\n  intrinsics: [400.0, 401.0, 319.5, 239.5]\n"
          "  distortion_model: equidistant\n  distortion_coeffs: [0.0, 0.0, 0.0, 0.0]\n"
          "  resolution: [640, 480]\n")

MALFORMED = [
    ("a.yaml", KALIBR.replace("[400.0, 401.0, 319.5, 239.5]", "[400.0, 401.0, 319.5]"),
     "cam0.intrinsics: expected 4 numbers, got 3"),
    ("a.yaml", KALIBR.replace("equidistant", "fov"), "cam0.distortion_coeffs: pinhole-fov takes 1"),
    ("a.yaml", KALIBR.replace("camera_model: pinhole", "camera_model: omni").replace(
        "equidistant", "fov"), "omni-fov has no registry model"),
    ("a.yaml", KALIBR.replace("  resolution: [640, 480]\n", ""), "cam0.resolution: missing"),
    ("a.yaml", KALIBR.replace("equidistant", "none").replace("0.0, 0.0, 0.0, 0.0", "0.1"),
     "cam0.distortion_coeffs: pinhole-none takes 0 coefficients, got 1"),
    ("a.yaml", KALIBR.replace("319.5, 239.5]", "319.5, abc]"),
     "cam0.intrinsics[3]: expected a number, got 'abc'"),
    ("a.yaml", KALIBR.replace("  intrinsics: [", "  intrinsics: [[\n"), "line "),
    ("c.txt", "# c\n1 PINHOLE 640 480 400 401 320\n", "line 2: PINHOLE takes 4 parameters"),
    ("c.txt", "1 PINHOLE 640 480 400 401 320 240\n2 PINHOLE 640 x 400 401 320 240\n",
     "line 2: expected CAMERA_ID MODEL WIDTH HEIGHT"),
    ("c.txt", "1 PINHOLE 640 480 400 401 320 240\n1 NOPE 640 480 1\n",
     "line 2: unknown COLMAP model 'NOPE'"),
    ("c.txt", "# c\n3 EQUIRECTANGULAR 400 200\n",
     "line 2: COLMAP's EQUIRECTANGULAR has no registry model (read: SIMPLE_PINHOLE"),
    ("b.json", '{"value0": {"intrinsics": [{"camera_type": "bal", "intrinsics": {}}], '
               '"resolution": [[640, 480]]}}', "value0.intrinsics[0].camera_type: 'bal'"),
    ("b.json", '{"value0": {"intrinsics": [{"camera_type": "ds", "intrinsics": {"fx": 1}}], '
               '"resolution": [[640, 480]]}}', "value0.intrinsics[0].intrinsics.fy: missing"),
    ("b.json", '{"value0": {"intrinsics": [}', "line 1: not valid JSON"),
    ("o.yaml", "%YAML:1.0\nCamera.type: \"Fisheye\"\nCamera1.fx: 1\n",
     "Camera.type: expected PinHole, KannalaBrandt8 or Rectified"),
    ("o.yaml", "%YAML:1.0\nCamera.type: \"KannalaBrandt8\"\nCamera1.fx: 1\nCamera1.fy: 1\n"
               "Camera1.cx: 1\nCamera1.cy: 1\nCamera.width: 640\nCamera.height: 480\n",
     "Camera1.k1: missing"),
    ("k.yml", "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\nK: !!opencv-matrix\n"
              "   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 0., 2., 0., 1., 2. ]\n",
     "line 5: !!opencv-matrix: rows x cols = 9, but data holds 6"),
    ("k.yml", "%YAML:1.0\n---\nimage_width: 640\nK: !!opencv-matrix\n"
              "   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 0., 2., 0., 1., 2., 0, 0, 1 ]\n",
     "image_height: missing"),
    ("k.yml", "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_model: \"fisheye\"\n"
              "K: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
              "   data: [ 1., 0., 2., 0., 1., 2., 0, 0, 1 ]\nD: [0.1, 0.2]\n",
     "D: expected 0 or 4 or 5 or 8 or 12 or 14 numbers, got 2"),
    ("a.json", '{"CameraCalibrations": [{"Label": "camera-rgb", "Projection": '
               '{"Name": "Spherical", "Params": [1, 2, 3]}}]}',
     "CameraCalibrations[0].Projection.Name: 'Spherical' has no registry model"),
    ("a.json", '{"CameraCalibrations": [{"Label": "camera-rgb", "Projection": '
               '{"Name": "FisheyeRadTanThinPrism", "Params": [1, 2, 3]}}]}',
     "CameraCalibrations[0].Projection.Params: FisheyeRadTanThinPrism takes 15"),
    ("a.json", '{"CameraCalibrations": [{"Label": "camera-x", "Projection": '
               '{"Name": "KannalaBrandtK3", "Params": [1, 1, 2, 2, 0, 0, 0, 0]}}]}',
     "CameraCalibrations[0].Projection.Params: the file gives no image size"),
    ("x.yaml", "foo: 1\nbar: [1, 2]\n", "no camera format recognised"),
    ("x.txt", "hello world\n", "no camera format recognised"),
]


@pytest.mark.parametrize("name,text,message", MALFORMED, ids=[m[2][:40] for m in MALFORMED])
def test_a_malformed_file_is_one_line_naming_the_file(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ValueError) as info:
        ot.Camera.load(path)
    text = str(info.value)
    assert text.startswith(str(path)) and "\n" not in text
    assert message in text


def test_a_truncated_cameras_bin(tmp_path):
    pytest.importorskip("pycolmap")
    _, folder = _colmap_binary(tmp_path, FILES / "colmap" / "fisheye-cameras.txt")
    raw = (folder / "cameras.bin").read_bytes()
    (tmp_path / "cut.bin").write_bytes(raw[:-5])
    with pytest.raises(ValueError, match=r"cut.bin: camera 2's parameters: the file ends early"):
        ot.Camera.load(tmp_path / "cut.bin")
    (tmp_path / "model.bin").write_bytes(struct.pack("<QIiQQ", 1, 7, 99, 10, 10))
    with pytest.raises(ValueError, match="unknown COLMAP model id 99"):
        ot.Camera.load(tmp_path / "model.bin")
    (tmp_path / "equi.bin").write_bytes(struct.pack("<QIiQQ", 1, 7, 17, 10, 10))
    with pytest.raises(ValueError, match="camera 7: COLMAP's EQUIRECTANGULAR has no registry"):
        ot.Camera.load(tmp_path / "equi.bin")


def test_unknown_name_format_and_missing_file(tmp_path):
    with pytest.raises(ValueError, match="no camera named 'cam7'; the file holds cam0, cam1"):
        ot.Camera.load(FILES / "kalibr" / "chain-omni-radtan.yaml", name="cam7")
    with pytest.raises(ValueError, match="format: expected one of json, ocamcalib"):
        ot.Camera.load(FILES / "kalibr" / "chain-omni-radtan.yaml", "yaml")
    with pytest.raises(FileNotFoundError):
        ot.Camera.load(tmp_path / "nothing.yaml")
    with pytest.raises(TypeError, match="expected a path, a pycolmap.Camera"):
        ot.Camera.load(42)


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------

def test_cli_info_takes_any_camera_file(tmp_path, capsys):
    # a small image keeps info's angular-resolution pass well under a second
    small = ot.Camera("double_sphere", [30.0, 30.0, 31.5, 23.5, -0.2, 0.6], (48, 64))
    path = small.save(tmp_path / "calib.json", "basalt")
    code = cli.main(["info", "--camera", str(path), "--name", "cam0"])
    out = capsys.readouterr().out
    assert code == 0
    assert "calib.json (cam0)" in out and "double_sphere" in out
    code = cli.main(["info", "--camera", str(path), "--camera-format", "kalibr"])
    assert code == 2 and "cam0" not in capsys.readouterr().out


def test_cli_a_malformed_camera_file_is_one_line_exit_2(tmp_path, capsys):
    path = tmp_path / "camchain.yaml"
    path.write_text(KALIBR.replace("[640, 480]", "[640]"))
    code = cli.main(["info", "--camera", str(path)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err
    assert err == (f"omniscape-torch info: error: {path}: cam0.resolution: expected 2 "
                   f"numbers, got 1")
    assert cli.main(["info", "--name", "cam0"]) == 2


def test_cli_convert_model_reads_a_camera_file(tmp_path, capsys):
    small = ot.Camera("kannala_brandt", [30.0, 30.0, 31.5, 23.5, 0.01, 0, 0, 0], (48, 64))
    path = small.save(tmp_path / "camchain.yaml", "kalibr")
    code = cli.main(["convert-model", "--camera", str(path), "--camera-format", "kalibr",
                     "--name", "cam0", "--to", "double_sphere", "--grid", "8"])
    out = capsys.readouterr().out
    assert code == 0
    assert f"source {path} (cam0) (kannala_brandt)" in out and "double_sphere" in out
