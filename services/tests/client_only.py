"""Run `crowdbake-submit` as the client distribution would, with the bake stack made unimportable.

    python client_only.py [submit arguments...]      # exits with submit's exit code

A meta-path finder refuses every module of the server's and the bake's dependencies (BLOCKED), so
an import of any of them anywhere in the client fails as it would in an environment that has only
the client's dependencies (pyproject.toml: httpx, tqdm).
"""
from __future__ import annotations

import importlib.abc
import sys

# Top-level modules of the `server` extra (pyproject.toml) that the client must not need.
BLOCKED = frozenset({
    "numpy", "scipy", "cv2", "PIL", "pyrender", "OpenGL", "trimesh", "meshoptimizer", "fast_simplification", "etcpak",
    "texture2ddecoder", "skimage", "matplotlib", "jsonschema", "fastapi", "starlette", "pydantic", "pydantic_settings",
    "multipart", "python_multipart", "uvicorn", "celery", "kombu", "redis", "sqlalchemy", "alembic", "prometheus_client",
    "fastapi_offline",
})


class BlockServerStack(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r} (blocked: the client must run without the bake stack)", name=name)
        return None


def install() -> None:
    for name in list(sys.modules):
        if name.split(".")[0] in BLOCKED:
            raise RuntimeError(f"{name} was imported before the blocker was installed")
    sys.meta_path.insert(0, BlockServerStack())


if __name__ == "__main__":
    install()
    from crowdbake.client.submit import main

    sys.exit(main(sys.argv[1:]))
