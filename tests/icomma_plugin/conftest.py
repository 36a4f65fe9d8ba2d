"""Fixtures shared by the localization tests (a module may define its own `demo`)."""
from __future__ import annotations

import pytest

from icomma_plugin.matchers import make_matcher


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """(demo scene at 96x96, its model, its cameras.json entries); a module may override it."""
    from icomma_plugin.app.demo_scene import build_demo_scene
    from icomma_plugin.io.cameras_json import read_cameras_json

    scene = build_demo_scene(tmp_path_factory.mktemp("demo") / "scene", seed=0, width=96,
                             height=96)
    return scene, scene.load_model(), read_cameras_json(scene.path / "cameras.json")


@pytest.fixture(scope="module")
def xfeat():
    return make_matcher("xfeat")
