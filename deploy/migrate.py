"""Database migrations for a deployment, run from the image (`python /app/deploy/migrate.py`).

Kubernetes runs the API with CROWDBAKE_MIGRATE_ON_START=false, so that several API replicas never
race to create the same tables: one Job upgrades the schema, and every API and worker pod first waits
in an initContainer until the database is at the migration its own code ships (`--wait`). During an
upgrade this keeps new pods from starting against the old schema, while old pods keep serving.

    python deploy/migrate.py              upgrade to the newest migration (idempotent)
    python deploy/migrate.py --wait 600   wait up to 600 s until the database is at the newest migration

Both read the database URL from the service's settings (CROWDBAKE_DATABASE_URL). Exit status 0 when
the database is at the newest migration, 1 otherwise.
"""
from __future__ import annotations

import argparse
import logging
import sys
import time

from sqlalchemy.exc import SQLAlchemyError

from crowdbake.settings import Settings
from crowdbake.storage.db import current_revision, head_revision, is_migrated, make_engine, migrate

logger = logging.getLogger("crowdbake.deploy.migrate")

# Seconds between two looks at the database while waiting; the Job takes seconds, not minutes.
WAIT_POLL_S = 2.0


def upgrade(settings: Settings) -> str:
    """Bring the database to the newest migration; returns the revision it is at."""
    engine = make_engine(settings.database_url)
    try:
        before = current_revision(engine)
        migrate(engine)
        after = current_revision(engine)
    finally:
        engine.dispose()
    logger.info("database migrated from %s to %s", before or "an empty schema", after)
    return after


def wait_until_migrated(settings: Settings, timeout_s: float, poll_s: float = WAIT_POLL_S) -> bool:
    """True once the database is at this code's newest migration, False after `timeout_s` seconds.

    An unreachable database counts as "not yet": the database may still be starting."""
    engine = make_engine(settings.database_url)
    deadline = time.monotonic() + timeout_s
    head = head_revision()
    try:
        while True:
            try:
                if is_migrated(engine):
                    logger.info("database is at migration %s", head)
                    return True
                state = f"at {current_revision(engine) or 'no migration'}, waiting for {head}"
            except SQLAlchemyError as error:
                state = f"unreachable ({type(error).__name__})"
            if time.monotonic() >= deadline:
                logger.error("database not migrated after %.0f s: %s", timeout_s, state)
                return False
            logger.info("database %s", state)
            time.sleep(poll_s)
    finally:
        engine.dispose()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--wait", type=float, metavar="SECONDS",
                        help="only wait (up to SECONDS) until another process has migrated the database")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    # Alembic announces every plugin and context at INFO; one line per outcome is what an operator reads.
    logging.getLogger("alembic").setLevel(logging.WARNING)
    settings = Settings()
    if args.wait is not None:
        return 0 if wait_until_migrated(settings, args.wait) else 1
    upgrade(settings)
    return 0


if __name__ == "__main__":
    sys.exit(main())
