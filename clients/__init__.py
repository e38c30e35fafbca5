"""Clients of the culling server: the OpenGL tile renderer (``clients.render``)."""
