import { McapIndexedReader, McapStreamReader } from "@mcap/core";
import { decompress } from "fzstd";
import { open, readFile } from "node:fs/promises";
const decompressHandlers = { zstd: (buf, size) => decompress(buf, new Uint8Array(Number(size))) };
for (const path of process.argv.slice(2)) {
  const fh = await open(path, "r");
  const readable = {
    size: async () => BigInt((await fh.stat()).size),
    read: async (offset, length) => { const b = Buffer.alloc(Number(length)); await fh.read(b, 0, Number(length), Number(offset)); return new Uint8Array(b.buffer, b.byteOffset, b.byteLength); },
  };
  const reader = await McapIndexedReader.Initialize({ readable, decompressHandlers });
  const counts = {};
  let n = 0, firstJson = null;
  for await (const msg of reader.readMessages()) {
    const topic = reader.channelsById.get(msg.channelId).topic;
    counts[topic] = (counts[topic] ?? 0) + 1; n++;
    if (!firstJson) firstJson = JSON.parse(new TextDecoder().decode(msg.data));
  }
  const schemas = [...reader.schemasById.values()].map((s) => s.encoding);
  // and as a stream, record by record, with CRC checks
  const stream = new McapStreamReader({ decompressHandlers, validateCrcs: true });
  stream.append(new Uint8Array(await readFile(path)));
  let records = 0; for (let r; (r = stream.nextRecord()); ) records++;
  console.log(JSON.stringify({ path, messages: n, counts, schemaEncodings: [...new Set(schemas)], metadata: [...reader.metadataIndexes].map((m) => m.name), streamRecords: records, streamDone: stream.done(), sample: firstJson }));
  await fh.close();
}
