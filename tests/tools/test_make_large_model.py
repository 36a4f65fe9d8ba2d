"""tools/make_large_model.py on a small demo model: split, check, write (or refuse)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from icomma_plugin.io.model_folder import load_model_folder
from tests.helpers.demo import demo_model


@pytest.fixture(scope="module")
def demo_folder(tmp_path_factory):
    scene, model = demo_model(tmp_path_factory.mktemp("demo48"), 48)
    return scene.path, model.num_gaussians


def test_split_checked_and_written(demo_folder, tmp_path, capsys):
    from tools.make_large_model import main

    src, P = demo_folder
    out = tmp_path / "big"
    rc = main(["-m", str(src), "-o", str(out), "--target", str(2 * P + 3), "--check-sides", "48",
               "--check-cameras", "2", "--distill-steps", "3"])
    assert rc == 0
    folder = load_model_folder(out)
    assert folder.model.num_gaussians == 2 * P + 3
    assert len(folder.cameras) == len(load_model_folder(src).cameras)
    # the source's principal point said in cfg_args (the demo folder's: upstream's centre)
    assert folder.cfg["principal_point"] == load_model_folder(src).principal_point == "centre"
    info = json.loads((out / "split.json").read_text())
    assert info["gaussians"] == 2 * P + 3 and info["mode"] == "preserve"
    assert info["distill_steps"] == 3 and len(info["checks_before_distill"]) == 2
    assert len(info["checks"]) == 2 and info["min_psnr_db"] >= 35.0
    assert "PSNR of split vs original" in capsys.readouterr().out


def test_refuses_below_min_psnr_and_bad_target(demo_folder, tmp_path, capsys):
    from tools.make_large_model import main

    src, P = demo_folder
    out = tmp_path / "upstream"
    rc = main(["-m", str(src), "-o", str(out), "--target", str(3 * P), "--mode", "upstream",
               "--check-sides", "48", "--check-cameras", "1", "--distill-steps", "0"])
    assert rc == 1 and not out.exists()
    assert "nothing written" in capsys.readouterr().err
    assert main(["-m", str(src), "-o", str(out), "--target", str(P - 1)]) == 2


def test_distilled_on_the_cameras_outside_the_check(demo_folder, tmp_path, monkeypatch):
    import icomma_plugin.fit.distillation as distill_module
    from tools.make_large_model import main

    src, P = demo_folder
    seen = {}

    def spy(student, teacher, cameras, steps, **kw):
        seen.update(cameras=list(cameras), steps=steps)
        return student

    monkeypatch.setattr(distill_module, "distill", spy)
    rc = main(["-m", str(src), "-o", str(tmp_path / "big"), "--target", str(P + 1),
               "--check-sides", "48", "--check-cameras", "2", "--distill-side", "24"])
    assert rc == 0 and seen["steps"] == 100  # the default
    folder = load_model_folder(src)
    step = len(folder.cameras) // 2
    checked = {tuple(np.asarray(e.w2c, dtype=np.float32).ravel())
               for e in folder.cameras[::step][:2]}
    fitted = {tuple(w2c.numpy().ravel()) for _, w2c in seen["cameras"]}
    assert len(seen["cameras"]) == len(folder.cameras) - 2 and not fitted & checked
    assert all(max(intr.width, intr.height) == 24 for intr, _ in seen["cameras"])
    # at most --distill-cameras of them, evenly spaced
    assert main(["-m", str(src), "-o", str(tmp_path / "few"), "--target", str(P + 1),
                 "--check-sides", "48", "--check-cameras", "2", "--distill-cameras", "3"]) == 0
    assert 2 <= len(seen["cameras"]) <= 3
    for bad in (["--distill-steps", "-1"], ["--distill-cameras", "0"]):
        assert main(["-m", str(src), "-o", str(tmp_path / "x"), "--target", str(P + 1),
                     *bad]) == 2
