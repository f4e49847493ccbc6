"""Links between rce's processes: the internal framing (:mod:`.framing`), framed links with
bounded queues (:mod:`.link`), control-plane RPC (:mod:`.rpc`), the data plane between endpoints
(:mod:`.dataplane`), a task set's link to its master (:mod:`.masterlink`), TLS (:mod:`.tls`),
the cluster key that authenticates internal links (:mod:`.cluster_auth`) and a TCP proxy that
cuts links for fault tests (:mod:`.tcpproxy`); a control link's op table (:mod:`.op_table`)."""
from rce.transport.cluster_auth import ClusterKey, Gate
from rce.transport.link import FramedLink
from rce.transport.op_table import OpTable
from rce.transport.rpc import RpcPeer

__all__ = ["ClusterKey", "FramedLink", "Gate", "OpTable", "RpcPeer"]
