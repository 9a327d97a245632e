"""Rewrites an MCAP recording with uncompressed chunks, message for message (same topics, schemas,
stamps and bytes), so that the replay benchmark can show what the node costs on an input with no
compression to undo, as a live feed has none:

    .venv/bin/python bench/mcap_uncompressed.py sim/samples/walk_switch.mcap /tmp/walk_plain.mcap
    S=/tmp/walk_plain.mcap; target/release/gdvae-node replay $S $S $S $S --config config/replay.toml
"""
import sys

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer


def main(source: str, target: str) -> None:
    with open(source, "rb") as inp, open(target, "wb") as out:
        reader = make_reader(inp)
        writer = Writer(out, compression=CompressionType.NONE)
        header = reader.get_header()
        writer.start(profile=header.profile, library="bench/mcap_uncompressed.py")
        schemas, channels = {}, {}
        for schema, channel, message in reader.iter_messages():
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                schema_id = schemas[schema.id] if schema is not None else 0
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, schema_id, channel.metadata
                )
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time, message.sequence
            )
        writer.finish()


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: mcap_uncompressed.py IN.mcap OUT.mcap")
    main(sys.argv[1], sys.argv[2])
