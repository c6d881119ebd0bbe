from dataclasses import dataclass

import pytest

from reloc_service.core.errors import ConfigError
from reloc_service.core.plugins import Registry, make_conf


@dataclass(frozen=True)
class Conf:
    k: int = 5
    ratio: float = 0.8
    kind: str = "sift"
    flag: bool = False


def test_make_conf_accepts_and_coerces():
    conf = make_conf(Conf, {"k": 3, "ratio": 1}, owner="x")
    assert conf == Conf(k=3, ratio=1.0)


@pytest.mark.parametrize("options, match", [
    ({"kk": 3}, "unknown option"),
    ({"k": "three"}, "expected int"),
    ({"flag": 1}, "expected bool"),
    ({"ratio": True}, "expected float"),
])
def test_make_conf_rejects(options, match):
    with pytest.raises(ConfigError, match=match):
        make_conf(Conf, options, owner="x")


def test_registry_duplicate_and_unknown():
    reg = Registry("widget")

    @reg.register("a")
    class A:
        pass

    assert reg.lookup("a") is A and A.name == "a"
    with pytest.raises(ValueError, match="duplicate"):
        reg.register("a")(A)
    with pytest.raises(ConfigError, match="unknown widget 'b'"):
        reg.lookup("b")
