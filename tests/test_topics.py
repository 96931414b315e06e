"""Topic maps (diffgcl.data.topics): every key validated with a one-line error naming it, command
units by hand, and the documentation covering every key."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from diffgcl.data.topics import (
    CommandSpec,
    TopicMapError,
    default_topic_map,
    key_reference,
    load_topic_map,
    other_boat_topic_map,
    parse_topic_map,
)

BASE = {"position": "/p", "heading": "/h", "commands": "/c"}
DOCS = Path(__file__).resolve().parents[1] / "docs" / "bags.md"


def _map(**changes):
    return parse_topic_map({**BASE, **changes}, "map.yaml")


@pytest.mark.parametrize(
    "changes, key, words",
    [
        ({"heading": {"topic": "/h", "frame": "nwu"}}, "heading.frame", "not one of enu, ned"),
        ({"position": {"topic": "/p", "time_source": "gps"}}, "position.time_source", "header"),
        ({"position": {"topic": "/p", "latency": -0.1}}, "position.latency", "minimum 0.0 s"),
        ({"position": {"topic": "/p", "bad_stamps": "drop"}}, "position.bad_stamps", "mask"),
        ({"position": {"topic": "/p", "max_gap": "long"}}, "position.max_gap", "a number"),
        ({"commands": {"topic": "/c", "thrust_unit": "hp"}}, "commands.thrust_unit", "percent"),
        (
            {"commands": {"topic": "/c", "thrust_unit": "percent"}},
            "commands.thrust_unit",
            "needs thrust_max",
        ),
        (
            {"commands": {"topic": "/c", "nozzle_unit": "fraction"}},
            "commands.nozzle_unit",
            "needs nozzle_max_deg",
        ),
        (
            {"commands": {"topic": "/c", "nozzle_positive": "left"}},
            "commands.nozzle_positive",
            "port, starboard",
        ),
        ({"radar": {"topic": "/r", "mount": [1, 2]}}, "radar.mount", "list of 3 numbers"),
        (
            {"radar": {"topic": "/r", "filter": {"min_intensty": 0.5}}},
            "radar.filter",
            "unknown key(s) ['min_intensty']",
        ),
        (
            {"radar": {"topic": "/r", "filter": {"min_range": 20, "max_range": 10}}},
            "radar.filter.max_range",
            "must exceed min_range",
        ),
        (
            {"radar": {"topic": "/r", "filter": {"persistence": {"scans": 2, "hits": 3}}}},
            "radar.filter.persistence.hits",
            "> scans",
        ),
        (
            {"radar": {"topic": "/r", "filter": {"persistence": {"scans": 1.5}}}},
            "radar.filter.persistence.scans",
            "an integer",
        ),
        ({"actuator_lags": {"thrust": -1}}, "actuator_lags.thrust", "minimum"),
        ({"segmentation": {"require_obstacle": "yes"}}, "segmentation.require_obstacle", "true"),
        ({"obstacle_search": {"ambiguous": "guess"}}, "obstacle_search.ambiguous", "skip, keep"),
        ({"datum": {"lat": 95, "lon": 10}}, "datum.lat", "maximum 90"),
        ({"lidar": {"topic": "scan"}}, "lidar.topic", "absolute topic name"),
    ],
)
def test_bad_keys_are_one_line_errors_naming_the_key(changes, key, words):
    with pytest.raises(TopicMapError) as info:
        _map(**changes)
    text = str(info.value)
    assert text.startswith(f"map.yaml: {key}"), text
    assert words in text and "\n" not in text


def test_unknown_and_missing_top_level_keys():
    with pytest.raises(TopicMapError, match=r"map.yaml: unknown key\(s\) \['speedo'\]"):
        _map(speedo="/s")
    with pytest.raises(TopicMapError, match=r"missing required role\(s\) \['commands'\]"):
        parse_topic_map({"position": "/p", "heading": "/h"}, "map.yaml")


def test_shipped_maps_parse_with_their_keys():
    odin = default_topic_map()
    assert odin.radar.filter.min_intensity == 0.55 and odin.radar.filter.persistence.coast == 1
    other = other_boat_topic_map()
    assert other.position.latency == 0.2 and other.velocity.frame == "ned"
    assert other.commands.thrust_unit == "percent" and other.commands.nozzle_positive == "starboard"
    assert other.actuator_lags.thrust == pytest.approx(1.95)
    assert other.obstacle is None and other.radar.filter.min_range == 15.0


def test_command_units_by_hand():
    spec = CommandSpec(
        "/c",
        thrust_unit="percent",
        thrust_max=12000.0,
        nozzle_unit="deg",
        nozzle_positive="starboard",
    )
    thrust, nozzle = spec.to_si([50.0, -10.0], [10.0, -30.0])
    np.testing.assert_allclose(thrust, [6000.0, -1200.0])
    np.testing.assert_allclose(nozzle, np.deg2rad([-10.0, 30.0]))  # to port is positive
    spec = CommandSpec("/c", thrust_unit="kN", nozzle_unit="fraction", nozzle_max_deg=30.0)
    thrust, nozzle = spec.to_si([1.5], [0.5])
    np.testing.assert_allclose([thrust[0], nozzle[0]], [1500.0, np.deg2rad(15.0)])
    spec = CommandSpec("/c", thrust_scale=2.0, nozzle_scale=-1.0)  # N, rad, then scales
    np.testing.assert_allclose(np.ravel(spec.to_si([3.0], [0.1])), [6.0, -0.1])


def test_yaml_file_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("position: [unclosed\n")
    with pytest.raises(TopicMapError, match="bad.yaml: invalid YAML"):
        load_topic_map(bad)
    with pytest.raises(TopicMapError, match="missing.yaml: cannot read"):
        load_topic_map(tmp_path / "missing.yaml")


def test_documentation_covers_every_key():
    text = DOCS.read_text()
    missing = []
    for path, *_ in key_reference():
        leaf = path.split(".")[-1]
        if f"`{leaf}`" not in text and f"{leaf}:" not in text:
            missing.append(path)
    assert not missing, f"docs/bags.md does not describe {missing}"
    # The annotated example in the documentation is a valid map.
    block = text.split("```yaml\n", 1)[1].split("```", 1)[0]
    parse_topic_map(yaml.safe_load(block), "docs/bags.md example")
