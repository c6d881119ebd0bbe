"""``reloc eval --remote``: the map uploaded through the client, trained and queried over Zenoh
scores like the in-process evaluation; and ``reloc demo`` end to end (slow)."""
# ruff: noqa: E402

from __future__ import annotations

# reloc_client lives in clients/ (importable once the distribution is installed).
import math

import cv2
import pytest
from service_support import endpoint, free_port, service_conf

from reloc_service.cli.main import main as reloc_main
from reloc_service.service.app import Service
from reloc_service.tools.data.dataset import DatasetEntry
from reloc_service.tools.data.dataset_write import write_dataset
from reloc_service.tools.eval.evaluate import RemoteSpec, evaluate

METHOD = "sbi+p3p"


@pytest.fixture(scope="module")
def scene_dataset(synthetic_scene, tmp_path_factory):
    """The conftest room as a reloc dataset v1 (6 map frames, 3 queries)."""
    root = tmp_path_factory.mktemp("room6")
    entries = {}
    for kind, images, poses in (("map", synthetic_scene.keyframe_images,
                                 synthetic_scene.keyframe_poses),
                                ("query", synthetic_scene.query_images,
                                 synthetic_scene.query_poses)):
        (root / kind).mkdir()
        entries[kind] = []
        for i, (image, pose) in enumerate(zip(images, poses, strict=True)):
            cv2.imwrite(str(root / kind / f"{i:03d}.png"), image)
            entries[kind].append(DatasetEntry(f"{kind}/{i:03d}.png", "cam0", pose))
    write_dataset(root, {"cam0": synthetic_scene.camera}, entries["map"], entries["query"])
    return root


@pytest.fixture(scope="module")
def service():
    port = free_port()
    with Service(service_conf(port, methods=[METHOD], default_method=METHOD)):
        yield endpoint(port)


@pytest.mark.slow
def test_remote_eval_scores_like_in_process(scene_dataset, service):
    local = evaluate(scene_dataset, METHOD, progress=False)
    remote = evaluate(scene_dataset, METHOD, progress=False,
                      remote=RemoteSpec(service, "evalmap"))
    assert remote.backend == f"remote {service} map evalmap"
    assert remote.map.keyframes == local.map.keyframes == 6
    lm, rm = local.method(METHOD), remote.method(METHOD)
    assert rm.summary.recall == lm.summary.recall
    assert rm.summary.relocalized == lm.summary.relocalized == 3
    for a, b in zip(lm.queries, rm.queries, strict=True):
        assert a.image_path == b.image_path and a.returned == b.returned
        assert math.isclose(a.t_err_m, b.t_err_m, abs_tol=0.01)
        assert b.matched_keyframe_ids and b.rank is not None
        assert "total" in b.timings_ms
    # A second run on the same map name starts from an emptied map.
    again = evaluate(scene_dataset, METHOD, progress=False,
                     remote=RemoteSpec(service, "evalmap"))
    assert again.map.keyframes == 6


def test_reloc_eval_remote_command(scene_dataset, service, capsys):
    code = reloc_main(["eval", str(scene_dataset), "-m", METHOD, "--remote", service,
                       "--map", "cli", "--no-progress"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert f"backend remote {service} map cli" in out and METHOD in out


def test_remote_eval_refuses_unserved_methods_and_options(scene_dataset, service):
    from reloc_service.core.errors import ConfigError

    with pytest.raises(ConfigError, match="does not serve"):
        evaluate(scene_dataset, "sbi+esm", progress=False, remote=RemoteSpec(service, "fresh"))
    with pytest.raises(ConfigError, match="does not serve"):     # now the map exists
        evaluate(scene_dataset, "sbi+esm", progress=False, remote=RemoteSpec(service, "fresh"))
    with pytest.raises(ConfigError, match="options"):
        evaluate(scene_dataset, METHOD, progress=False, options={"p3p": {}},
                 remote=RemoteSpec(service, "evalmap"))


@pytest.mark.slow
def test_reloc_demo_runs_end_to_end(capsys):
    code = reloc_main(["demo", "--scale", "0.5", "--no-progress"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "backend remote tcp/127.0.0.1:" in out and "@5cm/5deg" in out
