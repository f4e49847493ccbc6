"""The robot side of rce: the client library (:mod:`rce_client.connection`: ``Connection``,
``login``, ``hash_password``), ``rce-ros`` (:mod:`rce_client.rce_ros`, with its ROS 1 and ROS 2 bridges)
and the bus tools ``rce-topic``/``rce-service`` (:mod:`rce_client.tools`). Import from the module
that defines a name: a bus tool, which talks to a local bus and not to the cloud, then loads no
websocket client."""
