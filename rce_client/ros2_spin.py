"""One rclpy node spinning in a thread of its own beside an asyncio loop, and futures across the two.

rclpy runs callbacks in its executor; rce-ros runs in asyncio. :class:`Spinner` keeps them apart
(the pattern of rclpy's own docs, "Executors", and of ros2/examples' ``async`` demos): its own rclpy
``Context`` (``rclpy.init`` without rclpy's signal handlers: rce-ros handles SIGINT/SIGTERM), one
``Node``, and a ``SingleThreadedExecutor`` spun by one thread. Callbacks hand their work to the loop
(``loop.call_soon_threadsafe``, ``asyncio.run_coroutine_threadsafe``), never block the executor,
and come back with :meth:`Spinner.rclpy_future` (a loop's result awaited in an rclpy coroutine
callback, which yields to the executor meanwhile: a service answered minutes later blocks
nothing). :func:`asyncio_future` awaits an rclpy future (a service client's) in the loop.

A callback that raises does not stop the spinning: the error is logged and counted
(:attr:`Spinner.callback_errors`); :class:`NoAnswer` (a service call the bridge leaves unanswered,
already reported) is neither.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
import threading
from typing import Any

from rce.plumbing.log import get_logger

log = get_logger("rce.ros.ros2")


class NoAnswer(Exception):
    """Raised by a service callback whose call gets no response (ROS 2 services have no error reply;
    the caller's own timeout applies). The reason was logged where it happened."""


class Spinner:
    """rclpy context, node ``name`` and its executor thread; ``domain_id``: the ROS 2 domain of the
    context (None: ``ROS_DOMAIN_ID``'s), so one process can hold nodes of several graphs apart.

    ``node`` is made by :meth:`start` (in the caller's thread, before the thread spins);
    ``group`` is a reentrant callback group for every entity (a service call waiting for the cloud
    holds no other callback back). :meth:`close` stops the executor, joins the thread, destroys
    the node and shuts the context down."""

    def __init__(self, name: str, domain_id: int | None = None):
        self.name, self.domain_id = name, domain_id
        self.context: Any = None
        self.node: Any = None
        self.executor: Any = None
        self.group: Any = None
        self.callback_errors = 0
        self._thread: threading.Thread | None = None
        self._stopping = False

    def start(self) -> None:
        """``rclpy.init`` (own context, no signal handlers), the node, the executor thread. Raises what
        rclpy raises (an invalid node name: ``rclpy.exceptions.InvalidNodeNameException``)."""
        import rclpy
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.signals import SignalHandlerOptions

        self.context = Context()
        rclpy.init(args=["rce-ros"], context=self.context, domain_id=self.domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node(self.name, context=self.context, start_parameter_services=False, enable_rosout=False)
        self.group = ReentrantCallbackGroup()
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name=f"rclpy {self.name}", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException
        while not self._stopping:
            try:
                self.executor.spin_once()         # until work or the executor's shutdown
            except ExternalShutdownException:
                return
            except NoAnswer:
                pass
            except Exception as e:                # a callback's fault: the others go on
                self.callback_errors += 1
                log.warning("rclpy callback failed", node=self.name, error=f"{type(e).__name__}: {e}")

    def rclpy_future(self, fut: concurrent.futures.Future) -> Any:
        """An rclpy ``Future`` done when ``fut`` (from ``asyncio.run_coroutine_threadsafe``) is, its result
        ``fut`` itself; the executor is woken to resume whatever awaits it."""
        from rclpy.task import Future
        out = Future()

        def done(f: concurrent.futures.Future) -> None:
            out.set_result(f)
            self.executor.wake()
        fut.add_done_callback(done)
        return out

    def close(self, timeout: float) -> None:
        """Stop spinning (waiting up to ``timeout`` s for running callbacks), destroy the node, shut
        rclpy's context down; what :meth:`start` made of it, when it failed half-way. Blocking: call it in
        a thread."""
        import rclpy
        self._stopping = True
        if self.executor is not None:
            self.executor.shutdown(timeout_sec=timeout)
        if self._thread is not None:
            self._thread.join(timeout)
        if self.node is not None:
            self.node.destroy_node()
        if self.context is not None and self.context.ok():
            rclpy.shutdown(context=self.context)


def asyncio_future(rclpy_fut: Any, loop: asyncio.AbstractEventLoop) -> asyncio.Future:
    """An asyncio future of ``loop`` done with ``rclpy_fut`` (its result or exception; cancelled with it)."""
    out = loop.create_future()

    def settle(f: Any) -> None:
        if out.done():
            return
        if f.cancelled():
            out.cancel()
        elif f.exception() is not None:
            out.set_exception(f.exception())
        else:
            out.set_result(f.result())

    def done(f: Any) -> None:
        try:
            loop.call_soon_threadsafe(settle, f)
        except RuntimeError:               # the loop is closed: rce-ros is exiting
            pass
    rclpy_fut.add_done_callback(done)
    return out
