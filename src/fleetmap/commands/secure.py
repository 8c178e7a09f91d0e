"""``fleetmap secure``: the zenoh configs of a fleet that lets in only its own robots."""

from __future__ import annotations

import argparse
from pathlib import Path

from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.outputs import output_folder
from fleetmap.shared.io.security import SERVICES, check_fleet_roles, write_fleet_security


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "secure",
        help="write a fleet's authentication and access control (router and client zenoh configs)",
        description="Write DIR/router.json5 (users and passwords, default deny, and rules: robot rX may put only "
        "under fleet/NAME/robots/rX/** and hold only its own presence token, and may read the merger's outputs; "
        "the merger reads every robot and writes fleet/NAME/merger/**; the recorder and viewers only read) and "
        f"one client config per role (DIR/<robot>.json5, {', '.join(f'DIR/{s}.json5' for s in SERVICES)}) with "
        "its credentials and scouting off. Run the router with `fleetmap router --zenoh-config DIR/router.json5` "
        "and every robot and service with `--zenoh-config DIR/<role>.json5`. Passwords are random (256 bits); "
        "with --tls, also a fleet CA and one certificate per role (mutual TLS). Every file is readable by its "
        "owner only; nothing secret is printed. Copy to each host only its own config (and, with --tls, its "
        "key, certificate and ca.pem), at the same path: the configs name their files by absolute path.",
    )
    p.add_argument("--fleet", required=True, metavar="NAME", help="the fleet name (keys fleet/NAME/...)")
    p.add_argument("--robots", required=True, metavar="R1,R2,...", help="the robots allowed in, comma-separated")
    p.add_argument("--out", required=True, metavar="DIR", help="the folder to write (made owner-only)")
    p.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="where the router listens (repeatable; default tcp/127.0.0.1:7447, tls/... with --tls)",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="where robots and services reach the router, e.g. tcp/10.0.0.5:7447 (repeatable; default: --listen)",
    )
    p.add_argument("--tls", action="store_true", help="TLS with mutual authentication (tls/ endpoints)")
    existing = p.add_mutually_exclusive_group()
    existing.add_argument("--overwrite", action="store_true", help="replace the configs in DIR (new passwords for all)")
    existing.add_argument(
        "--keep-existing",
        action="store_true",
        help="if DIR already holds a fleet's configs, keep them and exit 0 (a deployment's first-start step)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    robots = [r.strip() for r in args.robots.split(",") if r.strip()]
    check_fleet_roles(args.fleet, robots)
    out = Path(args.out)
    if (out / "router.json5").exists() and args.keep_existing:
        print(f"fleetmap secure: {out.resolve()} already holds a fleet's configs; kept")
        return 0
    if (out / "router.json5").exists() and not args.overwrite:
        raise BadInput(
            str(out), "already holds a fleet's configs (router.json5); --overwrite replaces them, with new passwords"
        )
    out = output_folder(out, "--out")
    written = write_fleet_security(out, args.fleet, robots, args.listen or None, args.connect or None, tls=args.tls)
    print(f"fleetmap secure: fleet {args.fleet!r}, {len(robots)} robots, {len(written)} files in {out.resolve()}/")
    print(f"  router:  fleetmap router --zenoh-config {out.resolve()}/router.json5")
    robot = f"--robot {robots[0]} --fleet {args.fleet}"
    print(f"  robot:   fleetmap agent {robot} --zenoh-config {out.resolve()}/{robots[0]}.json5 ...")
    print(f"  merger:  fleetmap merger --fleet {args.fleet} --zenoh-config {out.resolve()}/merger.json5 ...")
    print(f"  record:  fleetmap record --fleet {args.fleet} --zenoh-config {out.resolve()}/recorder.json5 ...")
    return 0
