"""The SDK and `flashmono export` ask for the map's SH degree (default 0: no zero f_rest coefficients)."""

from __future__ import annotations

import pytest

from client import rest
from client.cli import build_parser


def test_map_request_carries_the_sh_degree():
    assert rest.map_ply("abc").params == {"sh_degree": 0}
    assert rest.map_ply("abc", 3).params == {"sh_degree": 3}
    with pytest.raises(ValueError, match="sh_degree"):
        rest.map_ply("abc", 4)


def test_export_command_defaults_to_degree_0_and_offers_3():
    parser = build_parser()
    assert parser.parse_args(["export", "abc"]).sh_degree == 0
    assert parser.parse_args(["export", "abc", "--sh-degree", "3"]).sh_degree == 3
    with pytest.raises(SystemExit):
        parser.parse_args(["export", "abc", "--sh-degree", "2"])


def test_map_format_picks_the_route_and_the_export_command_follows_format_or_suffix():
    from client.commands.export import chosen_format

    assert rest.map_ply("abc", format="spz").params == {"format": "spz"}
    assert rest.map_ply("abc", format="spz").path.endswith("/abc/map")
    assert rest.map_ply("abc").path.endswith("/abc/map.ply")
    with pytest.raises(ValueError, match="format"):
        rest.map_ply("abc", format="ksplat")
    assert chosen_format(None, None) == ("ply", "map.ply")
    assert chosen_format(None, "spz") == ("spz", "map.spz")
    assert chosen_format("out/room.splat", None) == ("splat", "out/room.splat")
    assert chosen_format("room.bin", "spz") == ("spz", "room.bin")
    assert chosen_format("-", None) == ("ply", "-")
    parser = build_parser()
    assert parser.parse_args(["export", "abc", "--format", "splat"]).format == "splat"
    with pytest.raises(SystemExit):
        parser.parse_args(["export", "abc", "--format", "ksplat"])
