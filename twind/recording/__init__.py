"""Sessions on disk: MCAP files of protobuf SampleBlocks (schemas/twind/v1)."""
