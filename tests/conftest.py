import os
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DARS_SHARED_DATA", ROOT / ".." / "shared" / "data")).resolve()
"""External data (NeRF Lego, fox, meshes, probes): ../shared/data beside the clone, or $DARS_SHARED_DATA."""
SAMPLE = ROOT / "samples" / "gallery"

os.environ.setdefault("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")
torch.set_num_threads(min(2, os.cpu_count() or 1))


def shared(*parts: str) -> Path:
    """Path under the external data folder, or skip the test (never download)."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"external data not present: {p} (set DARS_SHARED_DATA to the shared data folder)")
    return p


@pytest.fixture(scope="module")
def gl():
    """A headless moderngl context (EGL/llvmpipe) for a test module; without one the test is skipped, saying why."""
    from toolkit._checks import DarsError
    from viewers.preview import create_headless_context

    try:
        ctx = create_headless_context()
    except DarsError as e:
        pytest.skip(f"no headless OpenGL 3.3 context (EGL/llvmpipe): {e}")
    yield ctx
    ctx.release()


@pytest.fixture
def sample_scene_path() -> Path:
    if not (SAMPLE / "transforms_train.json").is_file():
        pytest.skip("bundled sample not rendered yet (samples/gallery)")
    return SAMPLE


@pytest.fixture
def sample_without_depth(tmp_path, sample_scene_path) -> Path:
    """A copy of the bundled sample whose frames carry no ground-truth depth maps (``nodepth``)."""
    import json
    import shutil

    scene = tmp_path / "nodepth"
    shutil.copytree(sample_scene_path, scene)
    for split in ("train", "test"):
        p = scene / f"transforms_{split}.json"
        doc = json.loads(p.read_text())
        for f in doc["frames"]:
            f.pop("depth_file_path", None)
        p.write_text(json.dumps(doc))
    return scene
