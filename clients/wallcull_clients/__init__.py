"""Clients of the culling server: the OpenGL tile renderer (``wallcull_clients.render``), the
simulated render nodes, the load driver and the load-test harness. They depend on the core
(protocol, wall, paths), never on the server or the command line."""
