"""The crowdbake client: what a CI pipeline or an artist's machine needs to bake on a crowdbake server.

It imports only the standard library, httpx and tqdm, so `pip install "crowdbake[client]"` (without
the bake stack: no numpy, pyrender or OpenCV) is enough to run `crowdbake-submit`. The full package
runs the same code as `crowdbake submit`, and also checks a downloaded bundle's binary formats.

    http.py      the server connection: retries with backoff, problem documents, exit codes
    progress.py  forward-only progress from successive bake records
    download.py  a published bundle, file by file, each sha256 checked
    submit.py    the `submit` command: arguments, preflight, upload, bake, follow, download
"""
