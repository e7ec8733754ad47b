"""The Sparkplug B payload schema (sparkplug_b.proto) and its generated protobuf module."""
