// prints the MCAP's message_start_time (ns) from its summary statistics
const { McapIndexedReader } = require("@mcap/core");
const { FileHandleReadable } = require("@mcap/nodejs");
const fs = require("fs/promises");
(async () => {
  const fh = await fs.open(process.argv[2], "r");
  const reader = await McapIndexedReader.Initialize({ readable: new FileHandleReadable(fh) });
  console.log(String(reader.statistics?.messageStartTime ?? [...reader.chunkIndexes].reduce((a, c) => (c.messageStartTime < a ? c.messageStartTime : a), BigInt(2) ** 63n)));
  await fh.close();
})();
