"""The lifecycles of the master's records, each a set of states and one table of the moves between
them, the way h11's ``_state.py`` keeps a connection's (every state a sentinel, every transition in
one dict, an illegal one a named error): a reader sees a container's and a node's whole life here,
and :class:`~rce_master.state.master_state.MasterState` moves a record only through
:func:`check_move`, which refuses a move the table does not have.

A container (docs/INTERNALS.md, "Container failover"; :mod:`rce_master.failover`,
:mod:`rce_master.placement.mover`)::

    starting --created--> running --its host or environment lost--> lost --re-created--> recovering
        \\--lost while created--> lost                                    recovering --created--> running
                                                                          recovering --lost again--> lost

A node (:class:`rce.contract.environment.NodeStatus`): ``starting`` when asked for (and again when its
container is re-created), ``running`` once its launch is answered, then what its environment's
launcher reports, from any state but ``running``'s own: ``started``, ``respawning``, ``exited`` (a
report after a missed one, or a re-registration's, may come in any order, so they may follow each
other freely; only the master's own ``running`` is kept for a node that was ``starting``).
"""
from __future__ import annotations

from enum import StrEnum
from typing import TypeVar

from rce.contract.environment import NodeStatus
from rce.plumbing.errors import RequestError


class ContainerState(StrEnum):
    """Where a container's record is in its life (module doc). A member is its ``str``, as stored."""
    STARTING = "starting"       # its CC runs (or a move's copy is made)
    RUNNING = "running"
    LOST = "lost"               # its host or environment went away; its records stay, for its re-creation
    RECOVERING = "recovering"   # being re-created, on the host its record names, under a new cid


#: A container's moves: state -> the states it may go to next.
CONTAINER_TRANSITIONS: dict[ContainerState, frozenset[ContainerState]] = {
    ContainerState.STARTING: frozenset({ContainerState.RUNNING, ContainerState.LOST}),
    ContainerState.RUNNING: frozenset({ContainerState.LOST}),
    ContainerState.LOST: frozenset({ContainerState.RECOVERING}),
    ContainerState.RECOVERING: frozenset({ContainerState.RUNNING, ContainerState.LOST}),
}

#: The container states with no container behind them (lost, or being re-created).
DOWN = frozenset({ContainerState.LOST, ContainerState.RECOVERING})

_REPORTED = frozenset({NodeStatus.STARTED, NodeStatus.RESPAWNING, NodeStatus.EXITED})

#: A node's moves: status -> the statuses it may take next (any may go back to ``starting``: its
#: container is re-created).
NODE_TRANSITIONS: dict[NodeStatus, frozenset[NodeStatus]] = {
    NodeStatus.STARTING: _REPORTED | {NodeStatus.RUNNING},
    NodeStatus.RUNNING: _REPORTED | {NodeStatus.STARTING},
    NodeStatus.STARTED: _REPORTED - {NodeStatus.STARTED} | {NodeStatus.STARTING},
    NodeStatus.RESPAWNING: _REPORTED - {NodeStatus.RESPAWNING} | {NodeStatus.STARTING},
    NodeStatus.EXITED: _REPORTED - {NodeStatus.EXITED} | {NodeStatus.STARTING},
}


class IllegalMove(RequestError):
    """A record asked to move where its lifecycle's table does not go (a bug, or a race the caller
    did not check for): nothing changed."""


S = TypeVar("S", ContainerState, NodeStatus)

#: Each lifecycle: its states' enum -> its table.
LIFECYCLES: dict[type, dict] = {ContainerState: CONTAINER_TRANSITIONS, NodeStatus: NODE_TRANSITIONS}


def check_move(kind: type[S], what: str, old: str, new: str) -> S:
    """``new`` as a state of lifecycle ``kind`` (:data:`LIFECYCLES`), when record ``what`` (e.g.
    ``container 'c1'``) may move there from ``old``; staying where it is, is no move. Raises
    :class:`IllegalMove` naming the record, both states and where it may go from ``old``, and
    :class:`ValueError` for a state that is not one of ``kind``'s."""
    table = LIFECYCLES[kind]
    old_state, new_state = kind(old), kind(new)
    if new_state != old_state and new_state not in table[old_state]:
        allowed = ", ".join(sorted(table[old_state]))
        raise IllegalMove(f"{what} cannot go from {old_state} to {new_state} (from {old_state}: {allowed})")
    return new_state
