"""moto's S3 service behind a WSGI server that keeps connections open (benchmarks only).

    python benchmarks/s3_keepalive.py HOST PORT

``python -m moto.server`` serves moto through Werkzeug's development server, which answers
every request with ``Connection: close`` (werkzeug/serving.py: "Always close the
connection"): each request then opens a TCP connection and a server thread, on the
client's and the server's CPU. S3 and the S3-compatible servers labs use (MinIO, Ceph)
keep HTTP/1.1 connections alive, and s3fs's client (aiohttp) reuses them. This serves the
same moto application through waitress (HTTP/1.1 keep-alive, 8 threads), so that
benchmarks/objstore.py can measure both. Each request is written to standard output as
``"METHOD /path"``, the form benchmarks/objstore.py counts in the Werkzeug log.
"""

from __future__ import annotations

import os
import sys


def main(argv=None) -> int:
    host, port = (argv or sys.argv[1:])[:2]
    os.environ.setdefault("MOTO_PORT", str(port))  # moto builds its URLs with it, as moto.server does
    from moto.moto_server.werkzeug_app import DomainDispatcherApplication, create_backend_app
    from waitress import serve

    app = DomainDispatcherApplication(create_backend_app)

    def logged(environ, start_response):
        query = environ.get("QUERY_STRING")
        print(f'"{environ["REQUEST_METHOD"]} {environ.get("PATH_INFO", "")}{"?" + query if query else ""}"',
              flush=True)
        return app(environ, start_response)

    serve(logged, host=host, port=int(port), threads=8, _quiet=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
