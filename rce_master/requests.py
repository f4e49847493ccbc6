"""The robot requests (docs/design.md, section 3.3: CC, DC, CN, CX), one handler each, in one table
(:data:`REQUESTS`), the way rosbridge_suite registers its capabilities
(``rosbridge_library/capabilities/``, listed in ``rosbridge_protocol.py``): adding a request
type, or a CN/CX component, touches one class and one table entry.

A request arrives as its type and data as the robot endpoint sent them (the wire form of the
model its session validated); :func:`handle` validates the data into its model with the same
function (:func:`rce.protocol.schema.validate`), once, and each handler reads the model's attributes.
The handler's body only asks
:class:`~rce_master.state.master_state.MasterState` (which enforces the rules) and tells the task sets
(:class:`~rce_master.control.Control`). Each component is a :class:`Step`: ``reserve`` (the state
change), ``tell`` (the I/O), ``confirm`` (the state change once told) and ``undo`` (when telling
failed). A step whose far end timed out may still have
been done there, so its undo takes it back on the far end too.

CN and CX are lists of components (:class:`Lists`): each item is handled on its own, in the
order of :data:`CN_STEPS`/:data:`CX_STEPS`; the refused ones are named together in one error.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rce.contract import environment as to_env
from rce.contract import host as to_host
from rce.plumbing.errors import RCEError, RequestError, Timeout
from rce.plumbing.log import get_logger
from rce.protocol import schema
from rce_master.control import Control
from rce_master.state.model import limits_of
from rce_master.state.master_state import MasterState

log = get_logger("rce.master")


@dataclass
class Request:
    """Who asks (``user``, ``robot``; the admin API asks with robot ``""``) and what answers."""
    user: str
    robot: str
    state: MasterState
    control: Control


class Step:
    """One component of a request (``item``: its model, :mod:`rce.protocol.schema`); ``key`` names
    its list in the request data."""
    key = ""

    def reserve(self, req: Request, item: Any) -> Any:
        """Change the state (validating); returns what :meth:`tell` and :meth:`undo` need."""
        return None

    async def tell(self, req: Request, item: Any, held: Any) -> Any:
        """Tell the task sets; returns their answer."""
        return None

    def confirm(self, req: Request, item: Any, held: Any, answer: Any) -> None:
        """Change the state once the task sets have done it."""

    async def undo(self, req: Request, held: Any, told: bool) -> None:
        """Take back :meth:`reserve` (and, when ``told``, what the far end did or may have done)."""

    async def run(self, req: Request, item: Any) -> Any:
        """Reserve, tell, confirm; undo when telling or confirming fails. Returns the answer."""
        held = self.reserve(req, item)
        try:
            answer = await self.tell(req, item, held)
        except Exception as e:
            await self.undo(req, held, told=isinstance(e, Timeout))
            raise
        try:
            self.confirm(req, item, held, answer)
        except Exception:
            await self.undo(req, held, told=True)
            raise
        return answer


# -- CC, DC ----------------------------------------------------------------------------------------------
class CreateContainerStep(Step):
    """CC ``{containerTag, containerData?}``: place it on a host, create it there, ST ``running``."""

    def reserve(self, req, item: schema.CCData):
        data = item.containerData.model_dump(exclude_unset=True) if item.containerData is not None else None
        return req.state.add_container(req.user, req.robot, item.cTag, data)[0]

    async def tell(self, req, item, container):
        return await req.control.create_container(container)

    def confirm(self, req, item, container, answer):
        req.state.container_ready(container, answer["data_addr"], answer.get("sandbox", ""))
        log.info("container created", user=req.user, ctag=container.ctag, cid=container.cid, tid=container.tid,
                 sandbox=container.sandbox)
        # the robot learns what isolation its container got ("namespaced", or "unconfined" on a host without root)
        req.control.notify_robot(req.user, req.robot, "ST", {"topic": "container", "cTag": container.ctag,
                                                             "status": "running", "sandbox": container.sandbox})

    async def undo(self, req, container, told):
        await req.control.tell_disconnects(req.state.container_failed(container))
        if told:
            await req.control.quiet(req.control.host_ask(container, to_host.DestroyContainer(cid=container.cid)))


class DestroyContainerStep(Step):
    """DC ``{containerTag}``: forget it with everything in it, disconnect its peers, destroy it.
    A lost container (or one being re-created) is forgotten at once, and its tag is free again."""

    def reserve(self, req, item: schema.DCData):
        return req.state.remove_container(req.user, item.cTag)

    async def tell(self, req, item, held):
        await req.control.destroy(*held)


# -- CN ----------------------------------------------------------------------------------------------------
class AddNode(Step):
    key = "addNodes"

    def reserve(self, req, spec: schema.NodeComponent):
        return req.state.add_node(req.user, spec)

    async def tell(self, req, spec, held):
        c, n = held
        await req.control.start_node(c, n.ntag, n.spec)

    def confirm(self, req, spec, held, answer):
        req.state.node_running(held[1])

    async def undo(self, req, held, told):
        c, n = held
        req.state.node_failed(n)
        if told:
            await req.control.quiet(req.control.host_ask(c, to_env.EnvRemoveNode(cid=c.cid, ntag=n.ntag)))


class RemoveNode(Step):
    key = "removeNodes"

    def reserve(self, req, spec: schema.NodeRef):
        return req.state.remove_node(req.user, spec.cTag, spec.nTag)

    async def tell(self, req, spec, container):
        await req.control.host_ask(container, to_env.EnvRemoveNode(cid=container.cid, ntag=spec.nTag))


class SetParam(Step):
    key = "setParam"

    def reserve(self, req, spec: schema.ParameterComponent):
        return req.state.container(req.user, spec.cTag)

    async def tell(self, req, spec, container):
        await req.control.host_ask(container, to_env.EnvSetParam(cid=container.cid, name=spec.name, value=spec.value))

    def confirm(self, req, spec, container, answer):
        req.state.set_param(req.user, container.ctag, spec.name, spec.value)


class DeleteParam(Step):
    key = "deleteParam"

    def reserve(self, req, spec: schema.ParameterRef):
        return req.state.delete_param(req.user, spec.cTag, spec.name)

    async def tell(self, req, spec, container):
        await req.control.host_ask(container, to_env.EnvDeleteParam(cid=container.cid, name=spec.name))


class AddInterface(Step):
    key = "addInterfaces"

    def reserve(self, req, spec: schema.InterfaceComponent):
        return req.state.add_interface(req.user, req.robot, spec)

    async def tell(self, req, spec, rec):
        await req.control.install_interface(rec)

    async def undo(self, req, rec, told):
        await req.control.tell_disconnects(req.state.interface_refused(rec))
        if told:
            await req.control.quiet(req.control.remove_interface(rec))


class RemoveInterface(Step):
    key = "removeInterfaces"

    def reserve(self, req, spec: schema.InterfaceRefs):
        return req.state.remove_interface(req.user, spec.eTag, spec.iTag)

    async def tell(self, req, spec, held):
        rec, pairs = held
        for a, b in pairs:
            other = b if a.iid == rec.iid else a
            await req.control.quiet(req.control.disconnect_end(other, rec.iid))
        await req.control.quiet(req.control.remove_interface(rec))


class ResizeContainer(Step):
    """CN ``resizeContainer`` (and the admin API's resize): new limits; the nodes keep running."""
    key = "resizeContainer"

    def reserve(self, req, spec: schema.ContainerComponent):
        return req.state.container(req.user, spec.cTag)

    async def tell(self, req, spec, container):
        return await req.control.host_ask(container, to_env.EnvResizeContainer(cid=container.cid,
                                                                            limits=limits_of(spec.model_dump())))

    def confirm(self, req, spec, container, answer):
        req.state.resize(req.user, container.ctag, limits_of(spec.model_dump()))


# -- CX ----------------------------------------------------------------------------------------------------
class ConnectStep(Step):
    key = "connect"

    def reserve(self, req, item: schema.ConnectionComponent):
        return req.state.connect(req.user, item.tagA, item.tagB)

    async def tell(self, req, item, held):
        await req.control.tell_connect(*held)

    async def undo(self, req, held, told):
        req.state.connection_failed(*held)
        await req.control.tell_disconnect(*held)          # one end may have connected already


class DisconnectStep(Step):
    key = "disconnect"

    def reserve(self, req, item: schema.ConnectionComponent):
        return req.state.disconnect(req.user, item.tagA, item.tagB)

    async def tell(self, req, item, held):
        await req.control.tell_disconnect(*held)


# -- the table -------------------------------------------------------------------------------------------
class Lists:
    """A request made of lists of components (CN, CX): every item of every step's list, in order."""

    def __init__(self, *steps: Step):
        self.steps = {s.key: s for s in steps}

    async def run(self, req: Request, data: schema.CNData | schema.CXData) -> None:
        """Raises one :class:`RequestError` naming every reason an item was refused for, each once
        (the other items are done)."""
        errors: list[str] = []
        for key, step in self.steps.items():
            for item in getattr(data, key):
                try:
                    await step.run(req, item)
                except RCEError as e:
                    errors.append(e.message)
        if errors:
            raise RequestError("; ".join(dict.fromkeys(errors)))


CN_STEPS = Lists(AddNode(), RemoveNode(), SetParam(), DeleteParam(), AddInterface(), RemoveInterface(),
                 ResizeContainer())
CX_STEPS = Lists(ConnectStep(), DisconnectStep())
REQUESTS: dict[str, Step | Lists] = {"CC": CreateContainerStep(), "DC": DestroyContainerStep(), "CN": CN_STEPS,
                                     "CX": CX_STEPS}


async def handle(req: Request, type_: str, data: dict) -> None:
    """Handle robot request ``type_`` (CC, DC, CN, CX) with its ``data`` as the robot sent it.
    Raises :class:`RCEError` (:class:`~rce.plumbing.errors.ProtocolError` for data the schema refuses)."""
    handler = REQUESTS.get(type_)
    if handler is None:
        raise RequestError(f"unknown request type {type_!r}")
    _, model = schema.validate({"type": type_, "data": data})
    await handler.run(req, model)
