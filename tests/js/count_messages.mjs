// Read an MCAP file with @mcap/core's indexed reader (what Foxglove builds on) and print,
// as JSON, what it found: messages per topic, message bytes per topic, the number of chunk
// indexes and the message count of the file's statistics.
//
// Usage: node count_messages.mjs FILE.mcap
// Exit 1 (with the error on stderr) if the reader cannot open the file.
import { open } from "node:fs/promises";
import { McapIndexedReader } from "@mcap/core";

/** An IReadable over a file handle: random access by offset and size (bigint, bytes). */
function fileReadable(handle) {
  return {
    size: async () => BigInt((await handle.stat()).size),
    read: async (offset, size) => {
      const buffer = new Uint8Array(Number(size));
      const { bytesRead } = await handle.read(buffer, 0, buffer.length, Number(offset));
      if (bytesRead !== buffer.length) {
        throw new Error(`short read: ${bytesRead} of ${size} bytes at ${offset}`);
      }
      return buffer;
    },
  };
}

const path = process.argv[2];
const handle = await open(path, "r");
try {
  const reader = await McapIndexedReader.Initialize({ readable: fileReadable(handle) });
  const topics = {};
  const bytes = {};
  for (const channel of reader.channelsById.values()) {
    topics[channel.topic] = 0;
    bytes[channel.topic] = 0;
  }
  for await (const message of reader.readMessages({ validateCrcs: true })) {
    const topic = reader.channelsById.get(message.channelId).topic;
    topics[topic] += 1;
    bytes[topic] += message.data.byteLength;
  }
  const statistics = reader.statistics?.messageCount;
  console.log(
    JSON.stringify({
      topics,
      bytes,
      chunk_indexes: reader.chunkIndexes.length,
      statistics_message_count: statistics === undefined ? null : Number(statistics),
    }),
  );
} finally {
  await handle.close();
}
