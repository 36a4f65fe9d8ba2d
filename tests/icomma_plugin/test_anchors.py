"""The model's source photos as anchors (ranking and PnP), and rival poses (ambiguity)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from icomma_plugin.io.datasets.base import ViewImage
from icomma_plugin.localization.anchors import PhotoAnchors, SourcePhoto
from icomma_plugin.localization.candidates import CandidateConfig
from icomma_plugin.localization.geometric import GeometricConfig, GeometricOutcome
from icomma_plugin.localization.localizer import Localizer
from icomma_plugin.localization.robust import RobustConfig, _rival
from icomma_plugin.localization.types import Query
from icomma_plugin.localization.verify import PoseScore, VerdictConfig, decide
from icomma_plugin.pose.convert import invert_rigid, perturb_pose
from icomma_plugin.render import render


class RenderedPhoto:
    """A dataset view whose image is a render of the model (a 'photo' of the demo scene)."""

    def __init__(self, model, intr, c2w, name):
        self.name, self.intrinsics, self.c2w = name, intr, c2w
        self.image_path = None
        with torch.no_grad():
            self.rgb = render(model, intr, torch.as_tensor(invert_rigid(c2w)).float(),
                              torch.zeros(3)).color.clamp(0, 1)

    def load_image(self, scale=1.0, background=None):
        from icomma_plugin.localization.types import resize_image

        intr = self.intrinsics.scaled(scale)
        return ViewImage(resize_image(self.rgb, intr.height, intr.width).clamp(0, 1), None, None)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    from icomma_plugin.app.demo_scene import build_demo_scene
    from icomma_plugin.io.cameras_json import read_cameras_json

    scene = build_demo_scene(tmp_path_factory.mktemp("demo") / "scene", seed=0, width=96,
                             height=96)
    model = scene.load_model()
    cams = read_cameras_json(scene.path / "cameras.json")
    photos = [SourcePhoto(c.img_name, c.c2w, scene.intrinsics,
                          RenderedPhoto(model, scene.intrinsics, c.c2w, c.img_name))
              for c in cams]
    return scene, model, cams, photos


def _counting(loc):
    """Record the photos each geometric round took correspondences from."""
    used = []
    original = loc.photos.correspondences

    def wrapped(*a, **k):
        X, x, names = original(*a, **k)
        used.append((names, len(X)))
        return X, x, names

    loc.photos.correspondences = wrapped
    return used


def test_photos_alone_carry_the_geometric_stage(demo, xfeat):
    scene, model, cams, photos = demo
    cfg = RobustConfig(geometric=GeometricConfig(anchors="photos"),
                       candidates=CandidateConfig(num_sampled=4))
    loc = Localizer(model, xfeat, cfg, cameras=cams, photos=photos, cache_dir=False)
    used = _counting(loc)
    init = perturb_pose(scene.gt_c2w, 20.0, 0.1, 3, pivot=scene.scene_centre)
    res = loc.localize(Query(scene.load_query(), scene.intrinsics), init, scene.gt_c2w)
    assert used and max(n for _, n in used) >= 30, used
    assert res.rot_err_deg < 0.1 and res.verdict.status == "ok", res.verdict.reason


def test_a_query_never_anchors_on_its_own_photo(demo, xfeat):
    scene, model, cams, photos = demo
    own = cams[2]
    cfg = RobustConfig(geometric=GeometricConfig(anchors="both", anchor_until_inliers=None),
                       candidates=CandidateConfig(num_sampled=4))
    loc = Localizer(model, xfeat, cfg, cameras=cams, photos=photos, cache_dir=False)
    used = _counting(loc)
    q = Query(photos[2].view.rgb, scene.intrinsics, name=own.img_name + ".png")
    init = perturb_pose(own.c2w, 10.0, 0.05, 4, pivot="camera")
    res = loc.localize(q, init)  # no truth given: left out by its name alone
    assert used and all(own.img_name not in names for names, _ in used)
    assert res.verdict.status == "ok" and res.rot_err_deg is None
    assert loc.own_cameras(None, own.img_name + ".jpg") == [own.img_name]


def test_nearest_photos_look_the_same_way(demo):
    _, _, cams, photos = demo
    anchors = PhotoAnchors(photos, torch.zeros(3))
    c2w = cams[5].c2w
    near = anchors.nearest(c2w, 2)
    assert near[0] == 5 and len(near) == 2
    assert 5 not in anchors.nearest(c2w, 2, exclude=frozenset({5}))
    behind = c2w.copy()
    behind[:3, :3] = behind[:3, :3] @ np.diag([-1.0, 1.0, -1.0])  # looking the other way
    assert all(i != 5 for i in anchors.nearest(behind, 3, max_angle_deg=60.0))


def test_cameras_with_photos_are_ranked_by_their_photos(demo, xfeat, tmp_path):
    scene, model, cams, photos = demo
    cfg = CandidateConfig(num_sampled=2)
    with_photos = Localizer(model, xfeat, cameras=cams, photos=photos[:3], cache_dir=tmp_path)
    index = with_photos.candidate_index(scene.intrinsics, cfg)
    assert index.kinds[:3] == ["photo"] * 3 and set(index.kinds[3:len(cams)]) == {"camera"}
    assert index.kinds[len(cams):] == ["sampled"] * 2
    renders = Localizer(model, xfeat, cameras=cams, cache_dir=tmp_path)
    renders.candidate_index(scene.intrinsics, cfg)
    assert renders.candidate_builds == 1  # another key: photos are part of it
    assert len(list((tmp_path / "candidates").glob("*.pt"))) == 2


def test_a_camera_named_like_a_photo_elsewhere_is_rendered(demo, xfeat):
    """Only the camera at the photo's pose is described by the photo of its name.

    A Blender folder names its train and test views alike (r_0 ...); a model's cameras.json lists
    both, and the source photos are the train views.
    """
    import dataclasses

    scene, model, cams, photos = demo
    twin = dataclasses.replace(cams[5], c2w=cams[1].c2w.copy())  # cams[5]'s name, another pose
    loc = Localizer(model, xfeat, cameras=list(cams) + [twin], photos=photos, cache_dir=False)
    index = loc.candidate_index(scene.intrinsics, CandidateConfig(num_sampled=0))
    assert index.source[5] == index.source[len(cams)] == cams[5].img_name
    assert index.kinds[5] == "photo" and index.kinds[len(cams)] == "camera"
    assert np.allclose(index.c2w[len(cams)], cams[1].c2w)


def _outcome(w2c, inliers, pnp):
    score = PoseScore(inliers + 10, inliers, 0.3, 0.3, 0.5, 0.9, 0.05)
    return GeometricOutcome(w2c, None, score, 3, True, pnp, 0.9, [pnp])


def test_a_far_hypothesis_that_agrees_almost_as_well_is_a_rival():
    cfg = RobustConfig()
    best = _outcome(np.eye(4), 200, 150)
    far = perturb_pose(np.eye(4), 30.0, 0.0, 0, pivot="camera")
    near = perturb_pose(np.eye(4), 2.0, 0.0, 1, pivot="camera")
    assert _rival([("a", best), ("b", _outcome(far, 40, 20))], best, cfg) is None  # far, weak
    assert _rival([("a", best), ("c", _outcome(near, 200, 150))], best, cfg) is None  # close
    rival = _rival([("a", best), ("d", _outcome(far, 190, 140))], best, cfg)
    assert rival["start"] == "d" and 29 < rival["rot_deg_apart"] < 31
    score = best.score
    ok = decide(score, VerdictConfig(), converged=True)
    amb = decide(score, VerdictConfig(), converged=True,
                 extra={"ambiguous": True, "rival": rival})
    assert ok.status == "ok" and amb.status == "uncertain" and "rival pose" in amb.reason


def test_photo_anchors_need_a_view_that_loads(demo):
    """A SourcePhoto made of a dataset view keeps its name, camera and intrinsics."""
    _, _, cams, photos = demo
    view = SimpleNamespace(name="IMG_1.jpg", c2w=cams[0].c2w, intrinsics=photos[0].intrinsics)
    p = SourcePhoto.of_view(view)
    assert p.name == "IMG_1.jpg" and np.array_equal(p.c2w, cams[0].c2w)
    assert PhotoAnchors([p], torch.zeros(3)).index_of("IMG_1.png") == 0


def test_the_photos_fingerprint_survives_a_copy_not_an_edit(tmp_path):
    """The candidate index's key of the source photos: by content, so a copied capture keeps it."""
    import os
    import shutil

    from icomma_plugin.camera import Intrinsics

    rng = np.random.default_rng(0)
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    for i in range(3):
        (a / f"p{i}.jpg").write_bytes(rng.bytes(200_000))  # larger than both samples
    shutil.copytree(a, b)
    os.utime(b / "p1.jpg", (1e9, 1e9))  # a copy made at another time

    def fingerprint(folder):
        photos = [SourcePhoto(f"p{i}.jpg", np.eye(4), Intrinsics(8, 8, 8.0, 8.0),
                              SimpleNamespace(image_path=str(folder / f"p{i}.jpg")))
                  for i in range(3)]
        return PhotoAnchors(photos, torch.zeros(3)).fingerprint()

    assert fingerprint(a) == fingerprint(b)
    data = bytearray((b / "p2.jpg").read_bytes())
    data[-10] ^= 0xFF  # an edit near its end
    (b / "p2.jpg").write_bytes(bytes(data))
    assert fingerprint(a) != fingerprint(b)
    (b / "p2.jpg").unlink()  # a photo gone
    assert fingerprint(a) != fingerprint(b)
