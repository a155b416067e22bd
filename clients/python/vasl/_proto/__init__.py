"""Generated gRPC stubs (private). Produced by clients/python/gen_proto.sh; not committed."""
