"""Zenoh key expressions: one per worker and purpose, one per object and purpose, under a namespace.

    {ns}/worker/{worker}            liveliness token, present while the worker runs
    {ns}/worker/{worker}/register   queryable: RegisterRequest -> ObjectInfo
    {ns}/worker/{worker}/info       queryable: InfoRequest -> WorkerInfo
    {ns}/obj/{name}/frame           subscriber: Frame (streamed, latest wins); queryable: Frame -> FrameAck
    {ns}/obj/{name}/query           queryable: QueryRequest -> QueryReply
    {ns}/obj/{name}/slice           queryable: SliceRequest -> SliceReply
    {ns}/obj/{name}/info            queryable: InfoRequest -> ObjectInfo
    {ns}/obj/{name}/delete          queryable: DeleteRequest -> Deleted
    {ns}/obj/{name}/mesh            queryable: MeshRequest -> MeshReply (newest applied vertices, faces)

A worker declares the object keys only for the objects it holds, so several workers can share a namespace
and Zenoh routes each request to the object's owner. Every queryable may also answer with an ErrorReply.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from badf.protocol._errors import InvalidNameError

MAX_NAME_LENGTH = 100
_NAME = re.compile(r"[A-Za-z0-9_.\-]+")


def check_name(name: object, *, what: str = "object name") -> str:
    """Return `name` if it can be one key-expression chunk: 1-100 of A-Z a-z 0-9 _ . -"""
    if not isinstance(name, str):
        raise InvalidNameError(f"{what} must be a string, got {type(name).__name__}")
    if not 0 < len(name) <= MAX_NAME_LENGTH or not _NAME.fullmatch(name):
        raise InvalidNameError(
            f"{what} must be 1 to {MAX_NAME_LENGTH} characters of A-Z a-z 0-9 _ . - (no '/', '*' or spaces), "
            f"got {name[:120]!r}"
        )
    return name


@dataclass(frozen=True)
class KeySpace:
    """The keys of one badf deployment. `namespace` is one or more name chunks joined by '/'."""

    namespace: str = "badf"

    def __post_init__(self) -> None:
        if not isinstance(self.namespace, str) or not self.namespace:
            raise InvalidNameError(f"namespace must be a non-empty string, got {self.namespace!r}")
        for chunk in self.namespace.split("/"):
            check_name(chunk, what=f"namespace chunk of {self.namespace!r}")

    def worker_token(self, worker: str) -> str:
        return f"{self.namespace}/worker/{check_name(worker, what='worker id')}"

    def worker_register(self, worker: str) -> str:
        return f"{self.worker_token(worker)}/register"

    def worker_info(self, worker: str) -> str:
        return f"{self.worker_token(worker)}/info"

    @property
    def every_worker_token(self) -> str:
        return f"{self.namespace}/worker/*"

    @property
    def every_worker_info(self) -> str:
        return f"{self.namespace}/worker/*/info"

    def _object(self, name: str, purpose: str) -> str:
        return f"{self.namespace}/obj/{check_name(name)}/{purpose}"

    def object_frame(self, name: str) -> str:
        return self._object(name, "frame")

    def object_query(self, name: str) -> str:
        return self._object(name, "query")

    def object_slice(self, name: str) -> str:
        return self._object(name, "slice")

    def object_info(self, name: str) -> str:
        return self._object(name, "info")

    def object_delete(self, name: str) -> str:
        return self._object(name, "delete")

    def object_mesh(self, name: str) -> str:
        return self._object(name, "mesh")

    @property
    def every_object_info(self) -> str:
        return f"{self.namespace}/obj/*/info"
