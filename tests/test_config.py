"""Service configuration: strict TOML loading, the embedded default, command-line overrides,
a smoke load of every file in config/, and what ``max_resident_mb`` cannot bound."""

import json
from pathlib import Path

import pytest
from service_support import free_port, service_conf

from reloc_service.core.errors import ConfigError
from reloc_service.service.config import (
    DEFAULT_CONFIG_FILE,
    ServiceConf,
    load_config,
    parse_config,
    with_overrides,
)

CONFIG_DIR = Path(__file__).resolve().parents[1] / "config"


def test_default_file_equals_the_embedded_default():
    assert DEFAULT_CONFIG_FILE.is_file()
    assert load_config(DEFAULT_CONFIG_FILE) == load_config(None) == ServiceConf()


def test_embedded_default_is_a_local_peer_without_router():
    conf = ServiceConf()
    assert conf.zenoh.mode == "peer"
    assert conf.zenoh.listen == ("tcp/127.0.0.1:7447",)
    assert conf.zenoh.connect == ()
    assert conf.zenoh.multicast_scouting is False


@pytest.mark.parametrize("doc, named", [
    ({"zenoh": {"listn": ["tcp/127.0.0.1:1"]}}, "listn"),
    ({"servce": {}}, "servce"),
    ({"service": {"worker": 3}}, "worker"),
    ({"limits": {"max_pixels": 3}}, "max_pixels"),
    ({"maps": {"lab": {"colour": "red"}}}, "colour"),
])
def test_unknown_keys_name_the_key_and_the_allowed_ones(doc, named):
    with pytest.raises(ConfigError) as info:
        parse_config(doc)
    assert named in str(info.value)
    assert "expected some of" in str(info.value)


@pytest.mark.parametrize("doc, fragment", [
    ({"zenoh": {"mode": "server"}}, "zenoh.mode"),
    ({"zenoh": {"listen": "tcp/127.0.0.1:7447"}}, "list of strings"),
    ({"service": {"workers": 0}}, "service.workers"),
    ({"service": {"workers": "2"}}, "expected int"),
    ({"service": {"opencv_threads": -1}}, "service.opencv_threads"),
    ({"service": {"blas_threads": -1}}, "service.blas_threads"),
    ({"service": {"worker_mode": "fork"}}, "service.worker_mode: expected one of"),
    ({"service": {"default_method": "ferns"}}, "default_method"),
    ({"service": {"prefix": "a/*"}}, "prefix"),
    ({"maps": {"bad name": {}}}, "whitespace"),
    ({"limits": {"max_payload_bytes": 0}}, "limits.max_payload_bytes"),
    ({"options": {"sbi": 3}}, "expected a table"),
])
def test_bad_values_are_config_errors(doc, fragment):
    with pytest.raises(ConfigError, match=fragment.replace("*", r"\*")):
        parse_config(doc)


def test_flags_override_the_file(tmp_path):
    path = tmp_path / "svc.toml"
    path.write_text('[zenoh]\nmode = "client"\nconnect = ["tcp/10.0.0.1:7447"]\n'
                    '[service]\nworkers = 3\nstorage = "/var/x"\n[maps.lab]\n'
                    '[options.verify]\nmin_inliers = 12\n')
    conf = load_config(path)
    assert conf.zenoh.mode == "client" and conf.service.workers == 3
    assert set(conf.maps) == {"lab"} and conf.options["verify"]["min_inliers"] == 12
    over = with_overrides(conf, mode="peer", listen=["tcp/127.0.0.1:9000"], storage="",
                          workers=1)
    assert over.zenoh.mode == "peer" and over.zenoh.listen == ("tcp/127.0.0.1:9000",)
    assert over.zenoh.connect == ("tcp/10.0.0.1:7447",)      # not given: kept
    assert over.service.workers == 1 and over.storage_path is None
    assert conf.service.worker_mode == "process"                   # the default
    assert with_overrides(conf, worker_mode="thread").service.worker_mode == "thread"
    assert with_overrides(conf) == conf


def test_zenoh_config_file_is_relative_to_the_toml(tmp_path):
    (tmp_path / "z.json5").write_text("{}")
    path = tmp_path / "svc.toml"
    path.write_text('[zenoh]\nconfig_file = "z.json5"\n')
    assert Path(load_config(path).zenoh.config_file) == tmp_path / "z.json5"


def test_invalid_toml_and_missing_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[zenoh\nmode=")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_config(tmp_path / "missing.toml")


@pytest.mark.parametrize("path", sorted(CONFIG_DIR.glob("*.toml")), ids=lambda p: p.name)
def test_every_toml_in_config_loads(path):
    conf = load_config(path)
    assert conf.service.default_method in conf.service.methods
    if conf.zenoh.config_file:
        assert Path(conf.zenoh.config_file).is_file()


@pytest.mark.parametrize("path", sorted(CONFIG_DIR.glob("*.json5")), ids=lambda p: p.name)
def test_every_zenoh_json5_in_config_loads(path):
    zenoh = pytest.importorskip("zenoh")
    conf = zenoh.Config.from_file(str(path))
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False


@pytest.mark.parametrize("service, message", [
    ({"worker_mode": "thread", "storage": ""}, "service.storage"),
    ({"worker_mode": "thread", "bootstrap_from_peers": True}, "bootstrap_from_peers"),
    ({"worker_mode": "thread", "max_resident_mb": -1}, "expected MB >= 0"),
])
def test_max_resident_mb_refuses_what_it_cannot_bound(service, message, tmp_path):
    """The bootstrap copies every map, and a map without storage cannot be reloaded: each
    refused by name."""
    with pytest.raises(ConfigError, match=message):
        service_conf(free_port(), **{"storage": str(tmp_path), "max_resident_mb": 100,
                                     **service})


def test_max_resident_mb_refuses_the_ros2_bridge(tmp_path):
    with pytest.raises(ConfigError, match=r"\[ros2\] enabled"):
        parse_config({"service": {"storage": str(tmp_path), "worker_mode": "thread",
                                  "max_resident_mb": 100},
                      "ros2": {"enabled": True}})
