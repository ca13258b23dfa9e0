"""The run's own ephemeral Prefect server (flows/ephemeral.py): a real uvicorn child serving
Prefect's API, its database seeded from a migrated template, a user's server left alone."""

from __future__ import annotations

import json
import shutil
import sqlite3
import urllib.request
from pathlib import Path

import pytest

from embody.flows.ephemeral import (EphemeralServer, database_template, prefect_api,
                                    save_template, seed_database)


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv("EMBODY_CACHE", str(tmp_path / "cache"))
    for name in ("PREFECT_API_URL", "PREFECT_API_DATABASE_CONNECTION_URL",
                 "PREFECT_SERVER_DATABASE_CONNECTION_URL"):
        monkeypatch.delenv(name, raising=False)
    return tmp_path / "cache"


def _rows(db: Path) -> dict[str, int]:
    with sqlite3.connect(db) as con:
        tables = [r[0] for r in con.execute(
            "SELECT name FROM sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%'")]
        rows = {t: con.execute(f'SELECT count(*) FROM "{t}"').fetchone()[0] for t in tables}
    con.close()
    return rows


def _revision(db: Path) -> str:
    with sqlite3.connect(db) as con:
        rev = con.execute("SELECT version_num FROM alembic_version").fetchone()[0]
    con.close()
    return rev


def _serve(home: Path) -> EphemeralServer:
    server = EphemeralServer(home, startup_timeout_s=180)
    server.start()
    return server


def test_first_server_saves_the_template_and_the_next_home_is_seeded(cache, tmp_path):
    first = _serve(tmp_path / "h1")
    try:
        assert not first.seeded  # no template yet: this server migrates its own database
        assert "PREFECT_SERVER_DATABASE_MIGRATE_ON_START" not in first._child_env()
        url = first.wait()
        pidfile = tmp_path / "h1" / "embody-servers" / f"{first.proc.pid}.json"
        assert json.loads(pidfile.read_text())["server"] == first.proc.pid
        with urllib.request.urlopen(f"{url}/health", timeout=10) as reply:
            assert json.loads(reply.read()) is True
    finally:
        first.stop()
    assert not first.alive() and not pidfile.exists()
    template = database_template()
    assert template.parent == cache / "prefect" and template.is_file()
    rows = _rows(template)
    assert len(rows) > 20 and rows["alembic_version"] == 1
    assert sum(rows.values()) == 1  # the schema only: no run's records
    assert _revision(template) == _revision(tmp_path / "h1" / "prefect.db")
    assert not Path(f"{template}-wal").exists()  # one self-contained file

    second = _serve(tmp_path / "h2")
    try:
        assert second.seeded
        # a copy of the migrated template: the server skips Alembic's check at its boot
        assert second._child_env()["PREFECT_SERVER_DATABASE_MIGRATE_ON_START"] == "false"
        url = second.wait()
        with urllib.request.urlopen(f"{url}/admin/version", timeout=10) as reply:
            assert reply.status == 200
        request = urllib.request.Request(f"{url}/flow_runs/filter", data=b"{}",
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=10) as reply:  # the schema is there
            assert reply.status == 200 and json.loads(reply.read()) == []
    finally:
        second.stop()
    assert _revision(tmp_path / "h2" / "prefect.db") == _revision(template)


def test_a_users_migration_setting_is_kept(tmp_path, monkeypatch):
    server = EphemeralServer(tmp_path / "h")
    server.seeded = True
    monkeypatch.setenv("PREFECT_API_DATABASE_MIGRATE_ON_START", "true")
    env = server._child_env()
    assert env["PREFECT_API_DATABASE_MIGRATE_ON_START"] == "true"
    assert "PREFECT_SERVER_DATABASE_MIGRATE_ON_START" not in env


def test_the_template_keeps_no_rows_and_an_existing_database_is_never_replaced(cache, tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    with sqlite3.connect(home / "prefect.db") as con:
        con.execute("CREATE TABLE alembic_version (version_num TEXT)")
        con.execute("INSERT INTO alembic_version VALUES ('abc')")
        con.execute("CREATE TABLE flow_run (id TEXT)")
        con.executemany("INSERT INTO flow_run VALUES (?)", [("r1",), ("r2",)])
    con.close()
    assert save_template(home)
    assert _rows(database_template()) == {"alembic_version": 1, "flow_run": 0}
    assert not save_template(home)  # kept: one template per Prefect version
    assert not seed_database(home)  # home has its database: never overwritten
    assert _rows(home / "prefect.db")["flow_run"] == 2
    fresh = tmp_path / "fresh"
    assert seed_database(fresh) and _revision(fresh / "prefect.db") == "abc"


def test_nothing_to_seed_or_save_with_another_database(cache, tmp_path, monkeypatch):
    unmigrated = tmp_path / "unmigrated"
    unmigrated.mkdir()
    sqlite3.connect(unmigrated / "prefect.db").close()
    assert not save_template(unmigrated) and not database_template().exists()
    template = database_template()
    template.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(unmigrated / "prefect.db", template)
    monkeypatch.setenv("PREFECT_API_DATABASE_CONNECTION_URL", "postgresql+asyncpg://db/prefect")
    assert not seed_database(tmp_path / "home")
    assert not (tmp_path / "home" / "prefect.db").exists()


def test_a_configured_api_is_used_as_is(cache, monkeypatch):
    import embody.flows.ephemeral as ephemeral

    monkeypatch.setenv("PREFECT_API_URL", "http://127.0.0.1:9/api")
    before = ephemeral._SERVER
    warmed = []
    with prefect_api(warm=lambda: warmed.append(1)) as url:
        assert url == "http://127.0.0.1:9/api"
    assert warmed == [1] and ephemeral._SERVER is before
