"""Database access: engines, sessions, and the Alembic migrations that ship inside the package.

SQLite (the default) is opened in WAL mode with a busy timeout, because the API and several worker
processes write to the same file: WAL lets readers proceed while one writer commits, and the timeout
turns "database is locked" into a short wait. PostgreSQL needs nothing special.
"""
from __future__ import annotations

import logging
import os
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from sqlalchemy import Engine, create_engine, event, inspect
from sqlalchemy.orm import Session, sessionmaker

logger = logging.getLogger(__name__)

MIGRATIONS_DIR = Path(__file__).resolve().parent / "migrations"
# Seconds a SQLite writer waits for another process's transaction before giving up.
SQLITE_BUSY_TIMEOUT_S = 30


def make_engine(url: str) -> Engine:
    """An engine for `url`; SQLite files get their folder created, WAL mode and a busy timeout."""
    if url.startswith("sqlite"):
        database = url.split("///", 1)[1] if "///" in url else ""
        if database and database != ":memory:":
            Path(database).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"timeout": SQLITE_BUSY_TIMEOUT_S, "check_same_thread": False})

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection, _record) -> None:
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA synchronous=NORMAL")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.close()

        return engine
    return create_engine(url, pool_pre_ping=True)


# A fork taken while another thread of this process is inside a SQLite transaction gives the child
# SQLite's in-process record of that lock with no thread left to release it: every write the child makes
# then waits out the busy timeout and fails ("database is locked") for the rest of its life. A Celery
# worker's main process writes from a background thread (the heartbeat of received messages) and forks
# pool processes from its main thread, so its sessions come from `fork_guarded_scope`, and a fork of
# this process waits until the guarded transaction has ended.
_fork_guard = threading.Lock()
os.register_at_fork(before=_fork_guard.acquire, after_in_parent=_fork_guard.release,
                    after_in_child=_fork_guard.release)


def make_sessionmaker(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(bind=engine, expire_on_commit=False)


@contextmanager
def session_scope(factory: sessionmaker[Session]) -> Iterator[Session]:
    """A session that commits on success and rolls back on any exception."""
    session = factory()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def _alembic_config(url: str):
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    # '%' is ConfigParser's interpolation character; URLs with escaped passwords contain it.
    config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return config


def migrate(engine: Engine) -> None:
    """Bring the database to the newest migration (a no-op when it is already there)."""
    from alembic import command

    config = _alembic_config(engine.url.render_as_string(hide_password=False))
    with engine.begin() as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, "head")


def current_revision(engine: Engine) -> str | None:
    """The migration the database is at, or None before the first one."""
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


def head_revision() -> str:
    """The newest migration shipped with this code."""
    from alembic.script import ScriptDirectory

    return ScriptDirectory.from_config(_alembic_config("sqlite://")).get_current_head()


def is_migrated(engine: Engine) -> bool:
    return inspect(engine).has_table("alembic_version") and current_revision(engine) == head_revision()


@contextmanager
def fork_guarded_scope(factory: sessionmaker[Session]) -> Iterator[Session]:
    """`session_scope` for a process that forks while other threads use the database: no fork of this
    process happens until the transaction has committed or rolled back. Never fork inside it."""
    with _fork_guard:
        with session_scope(factory) as session:
            yield session
