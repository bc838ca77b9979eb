"""`crowdbake keys`: mint, list and revoke API keys of a crowdbake server's database."""
from __future__ import annotations

import argparse
import sys

from crowdbake.cli.common import CommandError

DESCRIPTION = """\
API keys authenticate clients of the crowdbake server. A key is printed once, when it is created; the
database keeps only its sha256. Scopes: upload (assets), bake (start and follow bakes), publish (publish
bundles, make them public), read (read private bundles).

The database is the server's: give the same --data folder (or --database URL) as `crowdbake serve`, or
set CROWDBAKE_DATA_DIR / CROWDBAKE_DATABASE_URL."""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("keys", help="create, list and revoke API keys of a server", description=DESCRIPTION,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="keys_command", metavar="ACTION", required=True)

    def common(sub: argparse.ArgumentParser) -> None:
        sub.add_argument("--data", metavar="DIR", help="the server's data folder (default CROWDBAKE_DATA_DIR or ./crowdbake-data)")
        sub.add_argument("--database", metavar="URL", help="SQLAlchemy database URL (default CROWDBAKE_DATABASE_URL or a SQLite file in --data)")

    create = commands.add_parser("create", help="mint a key and print it (once)")
    create.add_argument("--scopes", required=True, help="comma-separated: upload,bake,publish,read")
    create.add_argument("--label", default="", help="a note saying who or what uses the key")
    common(create)
    create.set_defaults(func=run_create)

    listing = commands.add_parser("list", help="list keys (ids, scopes, labels; never the secrets)")
    common(listing)
    listing.set_defaults(func=run_list)

    revoke = commands.add_parser("revoke", help="revoke a key by its id")
    revoke.add_argument("key_id", metavar="ID", help="the key's id (the 12 hex digits after cbk_)")
    common(revoke)
    revoke.set_defaults(func=run_revoke)


def _sessions(args: argparse.Namespace):
    from pydantic import ValidationError

    from crowdbake.settings import Settings
    from crowdbake.storage.db import make_engine, make_sessionmaker, migrate

    overrides = {}
    if args.data:
        overrides["data_dir"] = args.data
    if args.database:
        overrides["database_url"] = args.database
    try:
        settings = Settings(**overrides)
    except ValidationError as error:
        raise CommandError(f"invalid settings: {error.errors()[0]['msg']}") from None
    engine = make_engine(settings.database_url)
    migrate(engine)
    return make_sessionmaker(engine)


def run_create(args: argparse.Namespace) -> int:
    from crowdbake.storage.db import session_scope
    from crowdbake.storage.keys import create_api_key, parse_scopes

    try:
        scopes = parse_scopes(args.scopes)
    except ValueError as error:
        raise CommandError(str(error)) from None
    with session_scope(_sessions(args)) as session:
        raw_key, record = create_api_key(session, scopes, args.label)
        key_id = record.id
    print(raw_key)
    print(f"key {key_id} with scopes {','.join(scopes)}; it is shown only now", file=sys.stderr)
    return 0


def run_list(args: argparse.Namespace) -> int:
    from sqlalchemy import select

    from crowdbake.storage.db import session_scope
    from crowdbake.storage.models import ApiKey

    with session_scope(_sessions(args)) as session:
        for record in session.scalars(select(ApiKey).order_by(ApiKey.created_at)).all():
            state = "revoked" if record.revoked_at else "active"
            print(f"{record.id}\t{state}\t{record.scopes.replace(' ', ',')}\t{record.label}")
    return 0


def run_revoke(args: argparse.Namespace) -> int:
    from crowdbake.storage.db import session_scope
    from crowdbake.storage.keys import revoke_api_key

    with session_scope(_sessions(args)) as session:
        if not revoke_api_key(session, args.key_id):
            raise CommandError(f"no active key {args.key_id!r}")
    print(f"key {args.key_id} revoked", file=sys.stderr)
    return 0
