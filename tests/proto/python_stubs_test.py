"""The Python stubs generated from our proto by the system protoc and
grpc_python_plugin import with Debian's python3-grpcio and behave: a Python
client needs nothing of our C++ code."""
import sys

import grpc
from framediffuser.v1 import image_pb2, render_service_pb2, render_service_pb2_grpc


def main() -> int:
    image = image_pb2.Image(width=8, height=8, channels=3, dtype=image_pb2.DTYPE_UINT8,
                            data=bytes(range(192)))
    req = render_service_pb2.RenderRequest(
        open=render_service_pb2.OpenSession(environment="demo", width=64, height=64, seed=7,
                                            steps=10, keyframe=image))
    parsed = render_service_pb2.RenderRequest.FromString(req.SerializeToString())
    assert parsed == req, "round trip changed the message"
    assert parsed.WhichOneof("kind") == "open"
    assert parsed.open.keyframe.data == bytes(range(192))

    svc = render_service_pb2.DESCRIPTOR.services_by_name["FrameDiffuser"]
    assert svc.full_name == "framediffuser.v1.FrameDiffuser"
    methods = {m.name: m for m in svc.methods}
    assert set(methods) == {"ListEnvironments", "Render"}, methods

    # A stub binds to a channel without contacting a server.
    channel = grpc.insecure_channel("127.0.0.1:1")
    stub = render_service_pb2_grpc.FrameDiffuserStub(channel)
    assert callable(stub.Render) and callable(stub.ListEnvironments)
    assert hasattr(render_service_pb2_grpc, "FrameDiffuserServicer")
    channel.close()
    print("python stubs OK (grpcio %s)" % grpc.__version__)
    return 0


if __name__ == "__main__":
    sys.exit(main())
