"""The benchmarks' loopback service: its config written as TOML is the one the service loads,
and ``reloc serve`` in a child process answers, then stops on SIGTERM."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest

from reloc_service.core.cameras import camera_from_dict
from reloc_service.service.config import load_config
from reloc_service.tools.bench.loopback import camera_client, loopback_service, toml_text


def test_toml_text_round_trips_a_service_config_through_the_service_loader(tmp_path):
    doc = {"zenoh": {"mode": "peer", "listen": ["tcp/127.0.0.1:7447"],
                     "multicast_scouting": False},
           "service": {"instance": "bench-1", "storage": str(tmp_path / "s \"q\""),
                       "workers": 3, "opencv_threads": 1, "fsync": False,
                       "methods": ["sbi+p3p", "ferns"], "default_method": "ferns"},
           "options": {"ferns": {"online": False, "min_posterior": 0.05}},
           "maps": {"bench": {}}}
    path = tmp_path / "service.toml"
    path.write_text(toml_text(doc))
    assert tomllib.loads(path.read_text()) == doc
    conf = load_config(path)
    assert conf.service.workers == 3 and conf.service.opencv_threads == 1
    assert conf.service.storage == str(tmp_path / "s \"q\"")
    assert dict(conf.options["ferns"]) == {"online": False, "min_posterior": 0.05}
    assert set(conf.maps) == {"bench"}


# reloc serve as a child process (about 6 s) is slow; the in-process service runs by default
@pytest.mark.parametrize("process", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_loopback_service_serves_and_applies_a_camera(tmp_path, process):
    storage = tmp_path / "storage"
    storage.mkdir()
    camera = camera_from_dict({"model": "pinhole", "width": 64, "height": 48,
                               "fx": 50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0})
    with loopback_service(storage, ["sbi+p3p"], {}, map_name="bench",
                          process=process) as endpoint:
        assert endpoint.startswith("tcp/127.0.0.1:")
        with camera_client(endpoint, "bench", "cam0", camera) as client:
            assert "cam0" in client.cameras(timeout=5)
            status = client.status(timeout=5)
            assert status is not None
    if process:  # its config and log were kept next to the storage
        logs = list(tmp_path.glob("service-*/service.log"))
        assert len(logs) == 1 and np.all([p.is_file() for p in logs])
