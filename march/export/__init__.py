"""``python -m march.export``: the student as an ONNX graph plus a deployment bundle.

:mod:`.bundle` writes the bundle and is the command line; :mod:`.deploy_spec` describes the G1
and the courses in the bundle's JSON; :mod:`.onnx_graph` builds and checks the deployment graph."""
