"""``schlieren tls init DIR``: a project CA and scheduler/worker/client certificates."""

from __future__ import annotations

import argparse

from schlieren.workers.cli import CLIError
from schlieren.workers.security import ROLES, make_certificates


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "tls",
        help="make TLS certificates for the cluster",
        description="Create the certificates Dask needs for mutual TLS between client, scheduler and workers.",
    )
    sub = p.add_subparsers(dest="tls_command", metavar="ACTION")
    sub.required = True
    init = sub.add_parser(
        "init",
        help="create a project CA and scheduler/worker/client certificates in DIR",
        description=(
            "Writes ca.pem, ca-key.pem and <role>.pem/<role>-key.pem for the roles "
            f"{', '.join(ROLES)} (keys mode 0600). Copy ca.pem plus the scheduler and worker files to the "
            "cluster; keep ca-key.pem elsewhere."
        ),
    )
    init.add_argument("directory", metavar="DIR")
    init.add_argument(
        "--host",
        action="append",
        dest="hosts",
        metavar="NAME",
        help="host name or IP the scheduler/workers are reached at (repeatable; default 127.0.0.1 and localhost)",
    )
    init.add_argument("--days", type=int, default=365, help="validity in days (default 365)")
    init.add_argument("--overwrite", action="store_true", help="replace an existing CA and certificates")
    init.set_defaults(func=handler)


def handler(args: argparse.Namespace) -> int:
    hosts = args.hosts or ["127.0.0.1", "localhost"]
    try:
        certs = make_certificates(args.directory, hosts, days=args.days, overwrite=args.overwrite)
    except FileExistsError as exc:
        raise CLIError(str(exc).replace("pass overwrite=True", "pass --overwrite")) from exc
    except (ValueError, OSError) as exc:
        raise CLIError(str(exc)) from exc
    print(f"wrote a CA and {', '.join(ROLES)} certificates for {', '.join(hosts)} to {certs.directory}")
    return 0
