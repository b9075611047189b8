"""Message classes built from the project's .proto files at run time.

``schemas/`` is the one source of the wire format: the descriptor set is compiled from it
with grpcio-tools' protoc when first needed, and MCAP files carry it, self-describing.
"""

from __future__ import annotations

import functools
import tempfile
from pathlib import Path

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from grpc_tools import protoc

from twind.errors import TwindError

SCHEMA_ROOT = Path(__file__).parent.parent / "schemas"  # a link to schemas/ in the source tree
TIMESERIES = "twind/v1/timeseries.proto"


@functools.cache
def _pool(proto: str) -> descriptor_pool.DescriptorPool:

    source = SCHEMA_ROOT / proto
    if not source.exists():
        msg = f"schema {source} not found: a broken installation of twind"
        raise TwindError(msg)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "set.binpb"
        code = protoc.main(["protoc", f"-I{SCHEMA_ROOT}", f"--descriptor_set_out={out}",
                            "--include_imports", str(source)])
        if code != 0:
            msg = f"protoc could not compile {source}"
            raise TwindError(msg)
        fds = descriptor_pb2.FileDescriptorSet.FromString(out.read_bytes())
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return pool


def message_class(full_name: str, proto: str = TIMESERIES) -> type:
    """The protobuf message class ``full_name`` (e.g. ``"twind.v1.SampleBlock"``).

    Parameters
    ----------
    full_name : str
        The message's full name, package included.
    proto : str
        The .proto file that defines it, relative to ``schemas/``.

    Returns
    -------
    type
        A protobuf message class.

    Raises
    ------
    TwindError
        If the .proto file is missing or protoc cannot compile it.
    """
    return message_factory.GetMessageClass(_pool(proto).FindMessageTypeByName(full_name))


def sample_block_class() -> type:
    """:class:`twind.v1.SampleBlock`."""
    return message_class("twind.v1.SampleBlock")
