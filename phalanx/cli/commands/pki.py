"""`phalanx pki`: a fleet's certificate authority, and a certificate per identity."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

pki_app = typer.Typer(
    help="A fleet's certificates: `init` a CA, `issue` identities, `list` them with expiry.",
    no_args_is_help=True,
)
FolderArg = Annotated[Path, typer.Argument(help="The PKI folder (ca.crt, <name>.crt/.key).")]
DaysOpt = Annotated[float, typer.Option(help="Validity, in days.", min=0.001)]


@pki_app.command("init")
def init(
    folder: FolderArg,
    fleet: Annotated[str, typer.Option(help="The fleet's name, in the CA's common name.")],
    days: DaysOpt = 3650.0,
    force: Annotated[
        bool, typer.Option(help="Replace an existing CA (every certificate it signed dies).")
    ] = False,
) -> None:
    """Create the fleet's certificate authority (keep ca.key off the robots)."""
    from phalanx.hosts.pki import init_ca

    crt = init_ca(folder, fleet=fleet, days=days, force=force)
    typer.echo(f"CA: {crt} (key {folder / 'ca.key'}, mode 0600)")


@pki_app.command("issue")
def issue(
    folder: FolderArg,
    names: Annotated[
        list[str] | None,
        typer.Argument(
            help="Common names: robot.ID, host.NAME, operator.NAME, viewer.NAME, world."
        ),
    ] = None,
    deployment: Annotated[
        str | None,
        typer.Option(help="Also every identity this deployment names (hosts with their address)."),
    ] = None,
    address: Annotated[
        list[str] | None,
        typer.Option("--address", help="A host's IP address or DNS name (repeatable)."),
    ] = None,
    days: DaysOpt = 365.0,
    missing_only: Annotated[
        bool, typer.Option(help="With --deployment: leave identities already issued alone.")
    ] = False,
) -> None:
    """Issue (or re-issue) keys and certificates signed by the CA in FOLDER."""
    from phalanx.hosts.pki import issue as issue_one

    wanted = [(n, tuple(address or ())) for n in names or ()]
    if deployment is not None:
        from phalanx.cli.commands.host import load_or_exit
        from phalanx.hosts.access import identities

        for ident in identities(load_or_exit(deployment).spec):
            if missing_only and (folder / f"{ident.common_name}.crt").exists():
                continue
            wanted.append((ident.common_name, ident.addresses))
    if not wanted:
        raise typer.BadParameter("name at least one identity, or give --deployment")
    for cn, addresses in wanted:
        crt, key = issue_one(folder, cn, days=days, addresses=addresses)
        where = f" for {', '.join(addresses)}" if addresses else ""
        typer.echo(f"{cn}: {crt}, {key} (0600){where}, {days:g} days")


@pki_app.command("list")
def list_(folder: FolderArg) -> None:
    """Every certificate in FOLDER, with its validity (expired ones marked)."""
    from phalanx.hosts.pki import list_issued

    for item in list_issued(folder):
        state = "EXPIRED" if item.expired() else "valid"
        names = f"  [{', '.join(item.names)}]" if item.names else ""
        typer.echo(
            f"{item.common_name:32s} {state:7s} until {item.not_after:%Y-%m-%d %H:%M} UTC{names}"
        )


def register(app: typer.Typer) -> None:
    """Add `phalanx pki`."""
    app.add_typer(pki_app, name="pki")
