"""``service unit NAME``: the systemd unit that runs ``cmion-mesh up`` for an embodiment
(docs/deploy.md, section systemd)."""

from __future__ import annotations

import argparse

from cmion_mesh.cli.common import subverb
from cmion_mesh.errors import ExitCode
from cmion_mesh.ops import systemd


def service_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Print the systemd unit that runs `cmion-mesh up` for embodiment NAME: save it as "
                          "/etc/systemd/system/cmion-mesh-NAME.service, then systemctl daemon-reload && systemctl "
                          "enable --now cmion-mesh-NAME. See docs/deploy.md.")
    sub = parser.add_subparsers(dest="service_command", required=True, metavar="ACTION")
    p = subverb(sub, "unit", "print the unit file of embodiment NAME (Type=notify, watchdog, hardened)",
                "cmion-mesh service unit robot --metrics 127.0.0.1:9464 > /etc/systemd/system/cmion-mesh-robot.service",
                description="Print the systemd unit file that runs `cmion-mesh up NAME` (Type=notify, a watchdog, "
                            "hardened): save it as /etc/systemd/system/cmion-mesh-NAME.service. See docs/deploy.md.")
    p.add_argument("name", metavar="NAME", help="the embodiment the unit runs")
    p.add_argument("--mesh", help="the deployment name given to up (default: the settings file's, else up's default)")
    p.add_argument("--metrics", metavar="HOST:PORT", help="serve metrics and /healthz there (given to up)")
    p.add_argument("--settings", metavar="FILE", dest="unit_settings",  # not `settings`: that one up reads (cli.main)
                   help=f"the daemon's settings file, an absolute path (default: {systemd.SETTINGS_PATH.format(name='NAME')})")
    p.add_argument("--watchdog", type=int, default=systemd.WATCHDOG_SEC, metavar="SECONDS",
                   help="WatchdogSec: a daemon whose update loop is stuck this long is restarted (default: %(default)s)")


def cmd_service(args: argparse.Namespace) -> int:
    print(systemd.unit(args.name, mesh=args.mesh, metrics=args.metrics, settings=args.unit_settings, watchdog_sec=args.watchdog),
          end="")
    return ExitCode.OK
