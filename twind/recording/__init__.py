"""Sessions on disk: MCAP files of protobuf SampleBlocks (schemas/twind/v1).

:mod:`.writer` and :mod:`.recorder` write them; :mod:`.reader` reads them
(:func:`~.reader.read_session`, :func:`~.reader.getdata`) with :mod:`.fastread` as its
engine, into the :mod:`.session` model; :mod:`.mcapfile` reads an MCAP file as far as it
goes; :mod:`.export`, :mod:`.replay` and :mod:`.recover` do what their commands say.
"""
