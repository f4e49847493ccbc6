"""The interfaces of the echo setup many engine tests use: a container's stringEcho.py
(Test package) reached through robot-side converters or forwarders ``req`` (robot -> node, on
/stringEchoReq) and ``resp`` (node -> robot, from /stringEchoResp)."""
from __future__ import annotations


def echo_interfaces(ctag: str, rid: str, side: str = "Converter", cls: str = "std_msgs/String") -> list[dict]:
    """CN ``addInterfaces`` components: container ``ctag``'s ``req``/``resp`` and robot ``rid``'s
    ``Subscriber{side}`` ``req`` and ``Publisher{side}`` ``resp``; connect ``ctag/X`` with ``rid/X``."""
    return [{"endpointTag": ctag, "interfaceTag": "req", "interfaceType": "PublisherInterface",
             "className": cls, "addr": "/stringEchoReq"},
            {"endpointTag": ctag, "interfaceTag": "resp", "interfaceType": "SubscriberInterface",
             "className": cls, "addr": "/stringEchoResp"},
            {"endpointTag": rid, "interfaceTag": "req", "interfaceType": f"Subscriber{side}", "className": cls},
            {"endpointTag": rid, "interfaceTag": "resp", "interfaceType": f"Publisher{side}", "className": cls}]
