"""``python -m march.export``: the student as an ONNX graph plus a deployment bundle.

:mod:`.bundle` writes the bundle and is the command line; :mod:`.onnx_graph` builds and checks the
deployment graph."""
