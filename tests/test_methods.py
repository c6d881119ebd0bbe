"""Method strings: MethodSpec's parse and canonical string (reloc_client/protocol/methods.py),
its ConfigErrors on the service side (core/methods.py), and the places that read methods
through it (the factory, the wire check, the served-method lookup, the benchmark)."""

import dataclasses
from types import SimpleNamespace

import pytest
from reloc_client import protocol as P
from reloc_client.protocol import MethodSpec, MethodStep

from reloc_service.algorithms.relocalizers.factory import (
    DEFAULT_METHOD,
    create_relocalizer,
    list_methods,
)
from reloc_service.core.errors import ConfigError
from reloc_service.core.map import KeyframeMap
from reloc_service.core.methods import parse_method
from reloc_service.service.codec import served_method
from reloc_service.tools.bench.accuracy import first_step_share

CANONICAL = ["sbi+p3p", "ferns", "sbi+p3p:orb", "bow+p3p,sbi+esm", DEFAULT_METHOD,
             "gt+none", "ferns,sbi+p3p:sift", "probe_orb"]


@pytest.mark.parametrize("text", CANONICAL)
def test_a_canonical_string_round_trips(text):
    spec = MethodSpec.parse(text)
    assert str(spec) == text
    assert MethodSpec.parse(str(spec)) == spec


def test_steps_name_place_pose_features_or_a_relocalizer():
    spec = MethodSpec.parse("sbi+p3p:orb,bow+p3p,ferns")
    assert spec.steps == (MethodStep(place="sbi", pose="p3p", features="orb"),
                          MethodStep(place="bow", pose="p3p"),
                          MethodStep(relocalizer="ferns"))
    assert [s.pose_label for s in spec.steps] == ["p3p:orb", "p3p", None]
    assert [str(s) for s in spec.steps] == ["sbi+p3p:orb", "bow+p3p", "ferns"]


def test_spaces_around_separators_are_dropped():
    assert str(MethodSpec.parse("  sbi + p3p : orb ,  bow+p3p ")) == "sbi+p3p:orb,bow+p3p"


def test_only_syntax_is_checked_names_are_left_to_the_registries():
    step, = MethodSpec.parse("nope+p4p:surf").steps
    assert (step.place, step.pose, step.features) == ("nope", "p4p", "surf")
    assert MethodSpec.parse("ferns:orb").steps == (MethodStep(relocalizer="ferns:orb"),)


def test_a_spec_is_frozen_and_hashable():
    spec = MethodSpec.parse("sbi+p3p,ferns")
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.steps = ()  # type: ignore[misc]
    assert {spec: 1}[MethodSpec.parse("sbi+p3p, ferns")] == 1


@pytest.mark.parametrize("text, expected", [
    ("", "empty method; expected e.g. 'sbi\\+p3p'"),
    ("   ", "empty method"),
    ("sbi+p3p,,ferns", "chain: empty step in 'sbi\\+p3p,,ferns'"),
    ("sbi+p3p,", "empty step"),
    ("a+b+c", "multi relocalizer: expected '<place>\\+<pose>' or "
              "'<place>\\+<pose>:<features>'.*got 'a\\+b\\+c'"),
    ("+p3p", "expected '<place>\\+<pose>'"),
    ("sbi+", "expected '<place>\\+<pose>'"),
    ("sbi+p3p:", "expected '<pose>:<features>'.*got 'p3p:'"),
    ("sbi+:orb", "expected '<pose>:<features>'.*got ':orb'"),
])
def test_malformed_methods_say_what_was_expected(text, expected):
    with pytest.raises(ValueError, match=expected) as raised:
        MethodSpec.parse(text)
    assert not isinstance(raised.value, ConfigError)  # the protocol knows no service errors
    with pytest.raises(ConfigError, match=expected):
        parse_method(text)


def test_parse_method_passes_a_spec_through():
    spec = MethodSpec.parse("bow+p3p")
    assert parse_method(spec) is spec


@pytest.mark.parametrize("kwargs", [
    {"place": "sbi"},                                        # no pose finder
    {"pose": "p3p"},                                         # no place finder
    {"relocalizer": "ferns", "place": "sbi", "pose": "p3p"},  # both forms
    {"relocalizer": "ferns", "features": "orb"},
    {"relocalizer": "a+b"},                                  # would print as place+pose
    {"place": "sbi", "pose": "p3p:orb"},                     # would print with features
    {"place": "sbi,bow", "pose": "p3p"},                     # would print as a chain
    {"place": " sbi", "pose": "p3p"},
    {"place": "", "pose": "p3p"},
])
def test_a_step_built_directly_must_print_as_itself(kwargs):
    with pytest.raises(ValueError, match="method step: expected"):
        MethodStep(**kwargs)


def test_a_spec_needs_steps():
    with pytest.raises(ValueError, match="one or more"):
        MethodSpec(())
    assert str(MethodSpec([MethodStep(relocalizer="ferns")])) == "ferns"


def test_the_factory_takes_a_string_or_a_spec():
    kmap = KeyframeMap()
    by_string = create_relocalizer("sbi+p3p:orb, sbi+none", kmap)
    by_spec = create_relocalizer(MethodSpec.parse("sbi+p3p:orb,sbi+none"), kmap)
    assert by_string.method == by_spec.method == "sbi+p3p:orb,sbi+none"
    assert create_relocalizer("sbi + p3p : orb", kmap).method == "sbi+p3p:orb"
    with pytest.raises(ConfigError, match="empty step"):
        create_relocalizer("sbi+p3p,,sbi+none", kmap)
    with pytest.raises(ConfigError, match="unknown relocalizer 'ferns:orb'"):
        create_relocalizer("ferns:orb", kmap)
    with pytest.raises(ConfigError, match="multi relocalizer: expected '<place>"):
        create_relocalizer("multi", kmap)


def test_every_listed_method_parses_to_itself():
    for listed in list_methods():
        assert str(MethodSpec.parse(listed["method"])) == listed["method"]


def _wire_method(method: str) -> str | None:
    camera = P.WireCamera("pinhole", 8, 6, 5.0, 5.0, 4.0, 3.0, ())
    request = P.RelocalizeRequest(P.WireImage(P.ImageFormat.MONO8, 8, 6, bytes(48)),
                                  camera=camera, method=method)
    return P.decode_relocalize_request(request.encode()).method


def test_the_wire_checks_the_chain_and_leaves_the_steps_to_the_service():
    assert _wire_method("sbi+p3p:orb, bow+p3p") == "sbi+p3p:orb, bow+p3p"
    assert _wire_method("a+b+c") == "a+b+c"  # not served: UNKNOWN_METHOD, from the service
    for bad in ("", "sbi+p3p,,ferns", "sbi + p3p"):
        with pytest.raises(P.ProtocolError) as raised:
            _wire_method(bad)
        assert raised.value.code is P.ErrorCode.BAD_VALUE


def test_a_served_method_is_found_by_its_canonical_string():
    served = ("sbi+p3p:orb,bow+p3p", "ferns")
    assert served_method("m", served, "ferns", None) == "ferns"
    assert served_method("m", served, "ferns", "sbi+p3p:orb, bow+p3p") == "sbi+p3p:orb,bow+p3p"
    for unknown in ("sbi+p3p", "a+b+c"):
        with pytest.raises(P.ProtocolError) as raised:
            served_method("m", served, "ferns", unknown)
        assert raised.value.code is P.ErrorCode.UNKNOWN_METHOD
        assert f"method {unknown!r} is not served on map 'm'" in raised.value.message


def test_the_benchmark_credits_a_chain_s_first_step_by_its_canonical_name():
    records = [SimpleNamespace(returned=True, method_used="sbi+p3p:orb"),
               SimpleNamespace(returned=True, method_used="bow+p3p"),
               SimpleNamespace(returned=False, method_used="bow+p3p")]
    share = first_step_share(MethodSpec.parse("sbi + p3p:orb, bow+p3p"), records)
    assert share == {"step": "sbi+p3p:orb", "answered": 1, "returned": 2,
                     "share_of_returned": 0.5}
