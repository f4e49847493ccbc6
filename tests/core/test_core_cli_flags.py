"""One name for one flag across the task sets: the address a task set is reached at is
``--advertise-host`` for rce-master, rce-robot and rce-container alike; the master's former
``--advertise`` still works (hidden from ``--help``, with a note on stderr)."""
from __future__ import annotations

import argparse

import pytest

from rce_container.cli import parser as container_parser
from rce_master import cli as master_cli
from rce_robot.cli import parser as robot_parser

TASK_SET_ARGS = {"rce-master": (master_cli.parser, []), "rce-robot": (robot_parser, ["127.0.0.1"]),
                 "rce-container": (container_parser, ["127.0.0.1"])}


@pytest.mark.parametrize("prog", sorted(TASK_SET_ARGS))
def test_every_task_set_takes_advertise_host(prog: str):
    make, positional = TASK_SET_ARGS[prog]
    p = make()
    assert p.parse_args([*positional, "--advertise-host", "rce.example"]).advertise_host == "rce.example"
    assert p.parse_args(positional).advertise_host is None
    assert "--advertise-host HOST" in p.format_help()


def test_the_masters_old_advertise_still_works_hidden_and_noted(capsys: pytest.CaptureFixture):
    p = master_cli.parser()
    args = p.parse_args(["--advertise", "old.example"])
    assert args.advertise_host == "old.example"
    assert "--advertise is deprecated; use --advertise-host" in capsys.readouterr().err
    assert "--advertise " not in p.format_help() and "--advertise\n" not in p.format_help()
    assert p.parse_args(["--advertise-host", "new.example"]).advertise_host == "new.example"
    assert capsys.readouterr().err == ""


class _Listening:
    """What :func:`rce_master.cli.start` needs of a master: it listens, then has its ports."""
    http_port, control_port = 9000, 8080

    async def start(self, *args) -> None:
        pass


@pytest.mark.parametrize("flags, host", [(["--advertise-host", "m1.example"], "m1.example"),
                                         (["--advertise", "m2.example"], "m2.example"),
                                         (["--bind", "127.0.0.2"], "127.0.0.2")])
async def test_the_master_advertises_the_advertise_host(flags: list[str], host: str):
    args: argparse.Namespace = master_cli.parser().parse_args(flags)
    info = await master_cli.start(args, _Listening())
    assert info["control"] == f"{host}:8080" and info["http"] == f"http://{host}:9000/"
