"""`crowdbake submit`: upload, bake on a server, follow and download (for CI).

The command lives in crowdbake.client.submit, which needs only httpx and tqdm, so the client
distribution (`pip install "crowdbake[client]"`, command `crowdbake-submit`) runs the same code.
"""
from __future__ import annotations

import argparse

from crowdbake.client import submit


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("submit", help="upload, bake on a server, follow and download (for CI)",
                                   description=submit.DESCRIPTION, epilog=submit.EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    submit.add_arguments(parser)
    submit.report_usage_errors_as_json(parser)
    parser.set_defaults(func=submit.run)
