"""The control plane's contract: every op between rce-master, robot endpoints, container hosts,
environments and nodes, as one typed model each, in one module per link, which both ends import
(docs/INTERNALS.md, "Control ops"):

- :mod:`rce.contract.base`: :class:`~rce.contract.base.OpArgs`, the base of every op's arguments, and
  :func:`~rce.contract.base.parse`, which names the link, the op and the key of a bad one;
- :mod:`rce.contract.master`: task set -> master (``register``, ``auth``, ``robot_request``, ...);
- :mod:`rce.contract.robot`: master -> robot task set;
- :mod:`rce.contract.host`: master -> container task set (its own ops; the others are an environment's);
- :mod:`rce.contract.environment`: container task set <-> environment, and a node's status;
- :mod:`rce.contract.node`: environment -> node (direct links, results, a move's state);
- :mod:`rce.contract.bus`: node -> bus;
- :mod:`rce.contract.handshake`: the cluster handshake's messages.

Each model's fields are the op's keys on the wire, unchanged; its ``OP`` is the op's name. A link's
:class:`~rce.transport.op_table.OpTable` parses what arrives into the model before its handler runs;
a sender builds the model and sends it (:meth:`rce.transport.rpc.RpcPeer.ask`, ``tell``).

The package sits in the engine's layers above :mod:`rce.interfaces` (interface types, lanes) and
below :mod:`rce.transport` and everything that talks on a link; it imports nothing else of rce but
:mod:`rce.plumbing`.
"""
