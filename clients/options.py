"""Option groups shared by the energyctl subcommands (as zenoh-python's examples/common.py does for its examples):
the Zenoh session, ``--set`` overrides, priority and CPUs, the log directory; and the help formatter."""

from __future__ import annotations

import argparse
import re
import textwrap
from collections.abc import Callable


class HelpFormatter(argparse.HelpFormatter):
    """argparse's formatter, except in descriptions and epilogs: paragraphs (separated by a blank line) stay apart,
    and a paragraph whose first line is indented is a block of lines, each wrapped on its own, its continuation
    lines indented as it is or, for "  name    text", under text (listings such as the config keys of
    ``energyctl run --help``). A text of one plain
    paragraph comes out exactly as argparse's own formatter would fill it."""

    def _fill_text(self, text, width: int, indent: str) -> str:
        text = str(text)  # a LazyText is made here
        out = []
        for para in re.split(r"\n[ \t]*\n", text.strip("\n")):
            if para[:1].isspace():
                lines = []
                for line in para.splitlines():
                    body = line.lstrip()
                    pad = indent + line[:len(line) - len(body)]
                    # "  name    text": continuation lines under text's column (if that leaves room), else under name
                    col = re.match(r"\s*\S+ {2,}", line)
                    hang = indent + " " * col.end() if col and col.end() < width // 2 else pad
                    lines.append(textwrap.fill(body, width, initial_indent=pad, subsequent_indent=hang) or pad)
                out.append("\n".join(lines))
            else:
                out.append(super()._fill_text(para, width, indent))
        return "\n\n".join(out)


class LazyText:
    """A description or epilog made only when the help is shown (HelpFormatter renders it): e.g. one that imports
    the config models, which the other commands need not load."""

    def __init__(self, make: Callable[[], str]):
        self.make = make

    def __str__(self) -> str:
        return self.make()

    def __contains__(self, part: str) -> bool:  # argparse looks for '%(prog)' in the text
        return part in str(self)


class Parser(argparse.ArgumentParser):
    """An ArgumentParser with HelpFormatter; its subparsers are Parsers too."""

    def __init__(self, *args, formatter_class=HelpFormatter, **kwargs):
        super().__init__(*args, formatter_class=formatter_class, **kwargs)


# ---------------------------------------------------------------------------------------------- --set overrides

def add_scenario_set(parser: argparse.ArgumentParser) -> None:
    """--set for the commands that run a scenario TOML."""
    parser.add_argument("--set", action="append", metavar="dotted.key=value",
                        help="override a scenario field, e.g. --set timing.delay_samples=2 "
                             "--set controller.K_per_s=800 (value parsed as TOML; repeatable)")


def add_config_set(parser: argparse.ArgumentParser, examples: str) -> None:
    """--set for the commands that read a process config (energyctl run / plant / load); examples: two keys of
    that config, as "--set a=1 --set b=2"."""
    parser.add_argument("--set", action="append", metavar="dotted.key=value",
                        help=f"override a key of the --config file, e.g. {examples} (value parsed as TOML; "
                             "repeatable; the keys are listed below)")


def add_config_command(subparsers, name: str, *, help: str, description: str, model: str, file: str,
                       example: str, set_examples: str, what: str) -> argparse.ArgumentParser:
    """A command that runs one process from its config (energyctl run / plant / load): --config FILE with the
    config's keys listed in the epilog (``model``: the class's name in schemas.component, imported only when the
    help is shown), and --set overrides. ``example``: one key=value for the epilog's explanation; ``what``: whose
    config it is."""

    def epilog() -> str:
        from clients.confighelp import config_epilog
        from schemas import component

        return config_epilog(getattr(component, model), file, example)

    p = subparsers.add_parser(name, help=help, description=description, epilog=LazyText(epilog))
    p.add_argument("--config", required=True, metavar=file, help=f"{what} config (TOML; its keys are listed below)")
    add_config_set(p, set_examples)
    return p


def add_core(parser: argparse.ArgumentParser) -> None:
    """--core: which implementation of the control core (and the plant's integrator) runs."""
    parser.add_argument("--core", choices=("auto", "c", "python"), default="auto",
                        help="the core's implementation: c (the compiled twin), python (the reference, about 25x "
                             "slower, the same bits), auto (c if it was built at install; the default)")


# ---------------------------------------------------------------------------------------------- priority, CPUs

def add_nice(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--nice", type=int, default=None, metavar="N",
                        help="realtime: nice value of controller and plant (default -10: above the load and the "
                             "recorder and forecast processes; 0 = no raise); recorder: of the paced loop (default: "
                             "as started). Raising needs CAP_SYS_NICE")


def role_cpus(text: str) -> dict[str, list[int]]:
    """--cpus: "controller=1,plant=0+1" -> {"controller": [1], "plant": [0, 1]} (argparse type)."""
    out: dict[str, list[int]] = {}
    for part in filter(None, text.split(",")):
        role, _, cpus = part.partition("=")
        if role not in ("controller", "plant", "load") or not cpus:
            raise argparse.ArgumentTypeError(f"{part!r}: expected controller|plant|load=CPU[+CPU]")
        try:
            out[role] = [int(c) for c in cpus.split("+")]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{part!r}: CPUs are numbers, joined by +") from None
    return out


def add_cpus(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cpus", type=role_cpus, default=None, metavar="ROLE=CPU[+CPU],...",
                        help="the CPUs controller, plant and load may each run on, e.g. controller=1,plant=0,load=0 "
                             "(their `cpus` config; default any); bench latency: controller= for the daemon and the "
                             "echo")


# ---------------------------------------------------------------------------------------------- logs

def add_logs(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--logs", default="logs", help="directory for the MCAP log (default: %(default)s)")


# ---------------------------------------------------------------------------------------------- Zenoh session

def add_zenoh(parser: argparse.ArgumentParser) -> None:
    """How a client command opens its Zenoh session (zenoh_from_args reads them back)."""
    parser.add_argument("--mode", choices=["peer", "client"], default="peer", help="Zenoh mode (default: peer)")
    parser.add_argument("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    parser.add_argument("--listen", action="append", metavar="ENDPOINT")
    parser.add_argument("--zenoh-config", metavar="FILE.json5", help="a Zenoh config file, passed through")
    parser.add_argument("--user", help="Zenoh user/password authentication: user name (with --password-file)")
    parser.add_argument("--password-file", metavar="FILE", help="file holding the password (mode 600)")
    parser.add_argument("--tls-root-ca", metavar="CA.pem", help="tls/ endpoints: the CA of the router's certificate")
    parser.add_argument("--tls-certificate", metavar="CERT.pem", help="mutual TLS: this client's certificate")
    parser.add_argument("--tls-private-key", metavar="KEY.pem", help="mutual TLS: its private key (mode 600)")


def zenoh_from_args(args: argparse.Namespace):
    """The ZenohConfig of add_zenoh's options."""
    from schemas.component import ZenohConfig, config_from_dict

    return config_from_dict(ZenohConfig, {"mode": args.mode, "connect": args.connect or [],
                                          "listen": args.listen or [], "config_file": args.zenoh_config,
                                          "user": args.user, "password_file": args.password_file,
                                          "tls_root_ca": args.tls_root_ca, "tls_certificate": args.tls_certificate,
                                          "tls_private_key": args.tls_private_key}, source="options")
