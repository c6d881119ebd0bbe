"""The deployment files: every TOML of config/ and deploy/ loads with the service's config
loader, every JSON5 with Zenoh's own parser, the systemd units, Dockerfile and compose file name
files that exist, deploy/README.md describes every file, and the companion-computer set-up
serves with its authentication on."""
# ruff: noqa: E402

from __future__ import annotations

import configparser
import json
import re
from pathlib import Path

import pytest
import zenoh
from reloc_client.client import RelocClient
from service_support import ROOT, Events, endpoint, free_port, wait_until

from reloc_service.core.cameras import PinholeCamera
from reloc_service.service.app import Service
from reloc_service.service.config import load_config, with_overrides
from reloc_service.service.zenoh_io import zenoh_config

DEPLOY = ROOT / "deploy"
TOMLS = sorted([*(ROOT / "config").glob("*.toml"), *DEPLOY.rglob("*.toml")])
JSON5S = sorted([*(ROOT / "config").glob("*.json5"), *DEPLOY.rglob("*.json5")])
UNITS = sorted(DEPLOY.rglob("*.service"))
CAMERA = PinholeCamera(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5)


def _id(p: Path) -> str:
    return str(p.relative_to(ROOT))


def test_the_deploy_tree_has_both_setups():
    for name in ("companion/reloc.service", "companion/reloc.toml", "ground/router.json5",
                 "ground/router-tls.json5", "ground/service-a.toml", "ground/service-b.toml",
                 "ground/service-replica.toml", "docker/Dockerfile", "docker/compose.yaml",
                 "README.md"):
        assert (DEPLOY / name).is_file(), name
    assert len(TOMLS) >= 7 and len(JSON5S) >= 8 and len(UNITS) >= 3


@pytest.mark.parametrize("path", TOMLS, ids=_id)
def test_every_toml_loads_and_builds_its_zenoh_config(path: Path):
    conf = load_config(path)
    zc = zenoh_config(conf.zenoh)          # the named JSON5 file too, keys on top
    assert json.loads(zc.get_json("mode")) == conf.zenoh.mode
    if conf.zenoh.config_file:
        assert Path(conf.zenoh.config_file).is_file()
    if path.is_relative_to(DEPLOY / "ground") and "service" in path.name:
        assert not conf.service.allow_new_maps and conf.maps, "a shard names its maps"
        assert conf.service.bootstrap_from_peers == ("replica" in path.name)


@pytest.mark.parametrize("path", JSON5S, ids=_id)
def test_every_json5_loads_with_zenoh(path: Path):
    conf = zenoh.Config.from_file(str(path))
    assert json.loads(conf.get_json("mode")) in ("peer", "client", "router")
    same = zenoh.Config.from_json5(path.read_text())
    assert same.get_json("mode") == conf.get_json("mode")
    acl = json.loads(conf.get_json("access_control"))
    if acl.get("enabled"):
        rules = {r["id"] for r in acl["rules"]}
        subjects = {s["id"] for s in acl["subjects"]}
        for policy in acl["policies"]:
            assert set(policy["rules"]) <= rules and set(policy["subjects"]) <= subjects


@pytest.mark.parametrize("path", UNITS, ids=_id)
def test_systemd_units_run_reloc_with_files_of_deploy(path: Path):
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.optionxform = str
    unit.read(path)
    assert {"Unit", "Service", "Install"} <= set(unit.sections())
    exec_start = unit["Service"]["ExecStart"].split()
    assert exec_start[0].endswith("/reloc") and exec_start[1] in ("serve", "router")
    config = exec_start[exec_start.index("--config") + 1]
    assert config.startswith("/etc/reloc/")
    name = Path(config).name
    candidates = [name] if "%i" not in name else ["service-a.toml", "service-b.toml"]
    for candidate in candidates:
        assert (path.parent / candidate).is_file(), f"{path.name}: {candidate} not in deploy"


def test_dockerfile_and_compose_reference_existing_files():
    dockerfile = (DEPLOY / "docker" / "Dockerfile").read_text()
    copied: set[str] = set()
    for line in re.findall(r"^COPY (.+?)$", dockerfile.replace("\\\n", " "), re.M):
        *sources, dest = line.split()
        for src in sources:
            assert (ROOT / src).exists(), f"Dockerfile: COPY {src}: no such file"
            copied.add(Path(src).name if dest.endswith("/etc/reloc/") else src)
    yaml = pytest.importorskip("yaml")
    compose = yaml.safe_load((DEPLOY / "docker" / "compose.yaml").read_text())
    for name, service in compose["services"].items():
        build = service["build"]
        context = (DEPLOY / "docker" / build["context"]).resolve()
        assert context == ROOT and (context / build["dockerfile"]).is_file(), name
        command = service["command"]
        config = Path(command[command.index("--config") + 1]).name
        assert config in copied, f"compose {name}: {config} is not copied into the image"
        for volume in service.get("volumes", []):
            source = volume.split(":")[0]
            if source.startswith("."):   # a bind mount: its example must exist
                example = (DEPLOY / "docker" / source).resolve()
                assert example.with_name(example.stem + ".example.txt").is_file() or \
                    example.is_file(), volume


def test_deploy_readme_mentions_every_file():
    readme = (DEPLOY / "README.md").read_text()
    for path in DEPLOY.rglob("*"):
        if path.is_file() and path.name != "README.md":
            assert path.name in readme, f"deploy/README.md does not mention {path.name}"


def test_companion_setup_serves_and_refuses_anonymous_sessions(tmp_path):
    port = free_port()
    creds = tmp_path / "credentials.txt"
    creds.write_text("ground:ground-pw\n")
    peer_json5 = tmp_path / "zenoh-peer.json5"
    peer_json5.write_text((DEPLOY / "companion" / "zenoh-peer.json5").read_text()
                          .replace("/etc/reloc/credentials.txt", str(creds)))
    toml = tmp_path / "reloc.toml"
    toml.write_text((DEPLOY / "companion" / "reloc.toml").read_text())
    conf = with_overrides(load_config(toml), listen=[endpoint(port)], storage=str(tmp_path / "s"),
                          instance="companion")
    with Service(conf):
        with pytest.raises(ConnectionError):
            RelocClient(endpoint(port), map="onboard")
        zc = zenoh.Config()
        zc.insert_json5("mode", '"client"')
        zc.insert_json5("transport/auth/usrpwd", json.dumps({"user": "ground",
                                                              "password": "ground-pw"}))
        with RelocClient(endpoint(port), map="onboard", config=zc, timeout=5) as client:
            events = Events(client)
            client.set_camera("c", CAMERA)
            events.wait("camera_added", id="c")
            status = wait_until(lambda: client.status(timeout=2))
            assert status.instance == "companion" and status.cameras == ("c",)
            events.close()
