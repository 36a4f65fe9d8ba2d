"""data.intrinsics.distortion: raw photos and frames are undistorted before they are localized.

The demo scene's photo is taken "through a lens" (a pinhole render remapped with known OpenCV
coefficients); localized with the coefficients it lands on the truth, without them it does not.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from icomma_plugin.app.inputs import LensDistortion, ProblemError
from icomma_plugin.pose.convert import perturb_pose
from tests.helpers.demo import demo_model, photo
from tests.helpers.tools import compose, localize_tool

SIZE = 100
DIST = (0.25, 0.1, 0.002, -0.003)  # strong, so that it matters at 100 px

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def _through_the_lens(img: np.ndarray, K: np.ndarray, dist) -> np.ndarray:
    """``img`` (a pinhole photo) as the camera with distortion ``dist`` would have taken it."""
    import cv2

    h, w = img.shape[:2]
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 1, 2)
    # where each pixel of the distorted photo looks, in the pinhole photo
    src = cv2.undistortPoints(grid.astype(np.float64), K, np.asarray(dist), P=K).reshape(h, w, 2)
    return cv2.remap(img, src[..., 0].astype(np.float32), src[..., 1].astype(np.float32),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


@pytest.fixture(scope="module")
def lens_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("lens")
    scene, model = demo_model(root / "model", SIZE)
    pinhole = photo(model, scene.intrinsics, scene.gt_c2w)
    K = scene.intrinsics.K().numpy()
    raw = _through_the_lens(pinhole, K, DIST)
    Image.fromarray(raw).save(root / "raw.png")
    start = perturb_pose(scene.gt_c2w, 3.0, 0.02, 1, pivot=scene.scene_centre)
    np.savetxt(root / "start.txt", start)
    np.savetxt(root / "gt.txt", scene.gt_c2w)
    return {"scene": scene, "root": root, "pinhole": pinhole, "raw": raw, "K": K}


def test_undistorting_gives_back_the_pinhole_photo(lens_scene):
    scene = lens_scene["scene"]
    lens = LensDistortion.from_config({"distortion": list(DIST)})
    raw = torch.from_numpy(lens_scene["raw"]).permute(2, 0, 1).float() / 255
    rgb, alpha, valid = lens.undistort(raw, None, scene.intrinsics)
    assert alpha is None and valid.shape == (1, SIZE, SIZE)
    assert float(valid.mean()) < 1.0 and bool(valid[0, SIZE // 2, SIZE // 2])  # corners lost
    pinhole = torch.from_numpy(lens_scene["pinhole"]).permute(2, 0, 1).float() / 255
    inner = (valid[0] > 0)
    inner[:10], inner[-10:], inner[:, :10], inner[:, -10:] = False, False, False, False
    before = (raw - pinhole).abs().mean(0)[inner].mean()
    after = (rgb - pinhole).abs().mean(0)[inner].mean()
    assert float(after) < 0.5 * float(before), (float(before), float(after))  # (two resamplings)


@pytest.mark.parametrize("raw, model, key", [
    ([0.1, 0.2, 0.3], "opencv", "data.intrinsics.distortion"),
    ("k1", "opencv", "data.intrinsics.distortion"),
    ([0.1, float("nan"), 0, 0], "opencv", "data.intrinsics.distortion"),
    ([0.1, 0.2, 0.0, 0.0, 0.1], "fisheye", "data.intrinsics.distortion"),
    ([0.1, 0.2, 0.0, 0.0], "brown", "data.intrinsics.distortion_model"),
])
def test_a_bad_distortion_is_one_error_naming_the_key(raw, model, key):
    with pytest.raises(ProblemError, match=key):
        LensDistortion.from_config({"distortion": raw, "distortion_model": model})


def test_no_or_zero_distortion_is_none_and_the_models_take_their_lengths():
    assert LensDistortion.from_config({}) is None
    assert LensDistortion.from_config({"distortion": [0, 0, 0, 0]}) is None
    assert LensDistortion.from_config({"distortion": [0.1, 0, 0, 0, 0.01]}).coefficients[4] == 0.01
    fish = LensDistortion.from_config({"distortion": [0.1, 0, 0, 0],
                                       "distortion_model": "fisheye"})
    assert fish.model == "fisheye"


def _localize(lens_scene, tmp_path, *extra):
    root = lens_scene["root"]
    cfg = compose([
        "data=model_folder", f"data.model_path={lens_scene['scene'].path}",
        f"data.query.image={root / 'raw.png'}", "data.intrinsics.camera=ring_000",
        f"data.init.c2w_file={root / 'start.txt'}", f"data.gt.c2w_file={root / 'gt.txt'}",
        "output.progress=false", "output.overlays=false", "output.match_lines=false",
        "output.convergence_plot=false", "output.trace_format=none", *extra])
    return localize_tool().run(cfg, tmp_path / "out")


def test_a_raw_photo_is_localized_with_its_distortion_and_not_without(lens_scene, tmp_path):
    dist = "[" + ",".join(map(str, DIST)) + "]"
    with_lens = _localize(lens_scene, tmp_path / "a", f"data.intrinsics.distortion={dist}")
    without = _localize(lens_scene, tmp_path / "b")
    assert with_lens["rot_err_deg"] < 0.2, with_lens["reason"]
    assert without["rot_err_deg"] > 2 * with_lens["rot_err_deg"], (without["rot_err_deg"],
                                                                   with_lens["rot_err_deg"])


def test_frames_are_undistorted_like_a_single_photo(lens_scene):
    """The tracker's query of a frame: the same remap, with its validity mask."""
    from icomma_plugin.app.tracking import _query

    scene = lens_scene["scene"]
    lens = LensDistortion.from_config({"distortion": list(DIST)})
    expected = lens.undistort(torch.from_numpy(lens_scene["raw"]).permute(2, 0, 1).float() / 255,
                              None, scene.intrinsics)
    frame = _query(lens_scene["raw"], scene.intrinsics, "f0", None, lens)
    assert torch.allclose(frame.rgb, expected[0], atol=1e-6)
    assert torch.equal(frame.valid, expected[2])
    assert _query(lens_scene["raw"], scene.intrinsics, "f0", None).valid is None


def test_a_batch_of_raw_photos_is_undistorted(lens_scene, tmp_path):
    import json

    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "raw.png").write_bytes((lens_scene["root"] / "raw.png").read_bytes())
    gt = tmp_path / "gt.json"
    gt.write_text(json.dumps({"raw.png": lens_scene["scene"].gt_c2w.tolist()}))
    start = tmp_path / "start.json"
    start.write_text(json.dumps({"raw.png": np.loadtxt(lens_scene["root"] / "start.txt").tolist()}))
    dist = "[" + ",".join(map(str, DIST)) + "]"
    out = tmp_path / "out"
    doc = localize_tool().run(compose([
        "data=model_folder", f"data.model_path={lens_scene['scene'].path}",
        f"data.queries={folder}", "data.intrinsics.camera=ring_000",
        f"data.init.poses_file={start}", f"data.gt.poses_file={gt}",
        f"data.intrinsics.distortion={dist}", f"output.dir={out}", "output.progress=false",
        "output.contact_sheet=false"]), out)
    (row,) = doc["photos"]
    assert row["status"] == "ok" and row["rot_err_deg"] < 0.2, row["reason"]


def test_a_camera_of_the_model_brings_its_datasets_lens(lens_scene, tmp_path):
    """data.intrinsics.camera: the source dataset's view of that camera gives its distortion.

    cameras.json keeps fx and fy only; a COLMAP dataset with the photo's OPENCV camera is the
    source (data.query.dataset, as cfg_args source_path would be).
    """
    from icomma_plugin.app.problem import _view_named
    from tests.helpers.colmap import qvec_tvec, write_colmap_bin

    scene, root = lens_scene["scene"], tmp_path / "dataset"
    (root / "images").mkdir(parents=True)
    (root / "images" / "ring_000.png").write_bytes((lens_scene["root"] / "raw.png").read_bytes())
    f = scene.intrinsics.fx
    # COLMAP's pixel centres are at +0.5: the image centre is (SIZE / 2, SIZE / 2) there
    cams = [(1, "OPENCV", SIZE, SIZE, [f, f, SIZE / 2, SIZE / 2, *DIST])]
    q, t = qvec_tvec(np.linalg.inv(scene.gt_c2w))
    write_colmap_bin(root / "sparse" / "0", cams, [(1, q, t, 1, "ring_000.png", [])], [])
    _view_named.cache_clear()
    res = _localize(lens_scene, tmp_path / "a", f"data.query.dataset={root}")
    assert res["rot_err_deg"] < 0.2, res["reason"]
    # an explicit distortion wins over the dataset's (here a wrong one: the pose suffers)
    res_wrong = _localize(lens_scene, tmp_path / "b", f"data.query.dataset={root}",
                          "data.intrinsics.distortion=[-0.25,0,0,0]")
    assert res_wrong["rot_err_deg"] > 2 * res["rot_err_deg"]
