"""Saved maps through the sync and async SDK and the `flashmono maps` CLI, against a real stack (the passthrough
engine: these tests are about the client; a real engine's map is saved in tests/service/test_maps.py)."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest
from live_stack import LiveStack
from map_samples import synthetic_package_bytes

from client.async_sdk import AsyncFlashMonoClient
from client.cli import main
from client.errors import BadRequestError, ConflictError, NotFoundError, PermissionDeniedError
from client.sdk import FlashMonoClient
from client.streaming import open_frames
from protocol.map_package import decode_package
from protocol.splats.ply_records import read_vertex_records

KEYS = "owner=stream;other=stream;reader=read"
DATA = Path(__file__).resolve().parents[1] / "data" / "icl_mini"


@pytest.fixture(scope="module")
def stack():
    with LiveStack(workers=1, api_keys=KEYS, engine="passthrough") as live:
        yield live


def test_the_sync_sdk_uploads_lists_reads_downloads_and_deletes_maps(stack, tmp_path):
    package = synthetic_package_bytes(name="kitchen", surfels=120)
    path = tmp_path / "kitchen.fmap"
    path.write_bytes(package)
    with FlashMonoClient(stack.url, api_key="owner") as client:
        saved = client.upload_map(path)
        assert saved.name == "kitchen" and saved.latest_version == 1 and saved.meta["surfels"] == 120
        renamed = client.upload_map(package, name="kitchen 2")
        assert renamed.name == "kitchen 2" and renamed.size_bytes == len(package)
        assert [m.id for m in client.list_maps().maps][:2] == [renamed.id, saved.id]
        assert [m.id for m in client.iter_maps(page_size=1)][:2] == [renamed.id, saved.id]
        got = client.get_map(saved.id)
        assert got.versions[0]["size_bytes"] == len(package) and got.sessions == []
        assert client.download_saved_map(saved.id, "package") == package
        assert len(read_vertex_records(client.download_saved_map(saved.id))) == 120
        assert len(client.download_saved_map(saved.id, "splat")) == 32 * 120
        assert decode_package(client.download_saved_map(saved.id, "package", version=1)).name == "kitchen"

        session = client.create_session(map_id=saved.id, map_mode="extend", name="in the kitchen")
        assert (session.map_id, session.map_version, session.map_mode) == (saved.id, 1, "extend")
        assert client.get_map(saved.id).sessions[0]["id"] == session.id
        with pytest.raises(ValueError, match="map_mode"):
            client.create_session(map_id=saved.id, map_mode="merge")
        with pytest.raises(BadRequestError, match="corrupt map package"):
            client.upload_map(package[:100])
        client.delete_map(renamed.id)
        with pytest.raises(NotFoundError):
            client.get_map(renamed.id)
    with FlashMonoClient(stack.url, api_key="other") as other:
        with pytest.raises(PermissionDeniedError):
            other.get_map(saved.id)
        with pytest.raises(PermissionDeniedError):
            other.create_session(map_id=saved.id)


def test_a_passthrough_sessions_map_cannot_be_saved(stack):
    frames = list(open_frames(DATA, max_frames=3, resize=(160, 120)))
    with FlashMonoClient(stack.url, api_key="owner") as client:
        session = client.create_session(name="no map")
        with pytest.raises(ConflictError, match="is created"):
            client.create_map(session.id, "too early")
        client.stream(session.id, frames)
        with pytest.raises(ConflictError, match="keeps no map to package"):
            client.create_map(session.id, "passthrough")


def test_the_async_sdk_has_the_same_map_calls(stack):
    async def run() -> None:
        async with AsyncFlashMonoClient(stack.url, api_key="owner") as client:
            saved = await client.upload_map(synthetic_package_bytes(name="async"))
            assert (await client.get_map(saved.id)).name == "async"
            assert saved.id in [m.id for m in (await client.list_maps(limit=50)).maps]
            assert len(await client.download_saved_map(saved.id, "splat")) == 32 * 200
            session = await client.create_session(map_id=saved.id)
            assert session.map_mode == "localize"
            await client.delete_map(saved.id)
            with pytest.raises(NotFoundError):
                await client.download_saved_map(saved.id)

    asyncio.run(run())


def test_the_maps_cli(stack, tmp_path, capsys):
    server = ["--server", stack.url, "--api-key", "owner"]
    package = tmp_path / "cli.fmap"
    package.write_bytes(synthetic_package_bytes(name="cli map"))
    assert main(["maps", "upload", str(package), "--name", "from the cli", *server]) == 0
    map_id = capsys.readouterr().out.split()[0]
    assert main(["maps", "list", *server]) == 0
    listing = capsys.readouterr().out
    assert "SURFELS" in listing and map_id in listing and "from the cli" in listing
    assert main(["maps", "show", map_id, *server]) == 0
    assert json.loads(capsys.readouterr().out)["meta"]["name"] == "cli map"
    out = tmp_path / "map.spz"
    assert main(["maps", "download", map_id, "--format", "spz", "--out", str(out), *server]) == 0
    assert out.read_bytes()[:2] == b"\x1f\x8b"  # gzip
    assert main(["maps", "download", map_id, "--out", str(tmp_path / "back.fmap"), *server]) == 0
    assert (tmp_path / "back.fmap").read_bytes() == package.read_bytes()
    assert main(["maps", "create", "--from-session", "f" * 32, "--name", "x", *server]) == 1
    assert "not found" in capsys.readouterr().err
    assert main(["maps", "delete", map_id, *server]) == 0
    assert main(["maps", "show", map_id, *server]) == 1
