"""The badf client: needs only numpy and zenoh.

    from badf.client import Client
    with Client("tcp/127.0.0.1:7447") as client:
        obj = client.register("bunny", vertices, faces, depth=7, sign="auto")
        obj.update(new_vertices)                  # blocks until applied; returns the frame number
        obj.stream(new_vertices)                  # does not wait; the worker keeps the newest
        res = obj.query(points, outputs=("distance", "normal"))
        res.distance, res.normal, res.frame

Errors are the exception types of badf.protocol (for example ObjectNotFoundError, WorkerUnavailableError).
"""

from badf.client._client import Client, RemoteObject

__all__ = ["Client", "RemoteObject"]
