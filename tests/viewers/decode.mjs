// node decode.mjs RUN.mcap: decode every message of a run log as Lichtblick / Foxglove would, with the packages
// they decode with: @mcap/core reads the file; CDR goes through @lichtblick/rosmsg (ros2msg schema text) and
// @lichtblick/rosmsg2-serialization; protobuf through protobufjs from the schema's FileDescriptorSet; JSON is
// parsed and its JSON Schema held to the rules under which the apps build a channel's field list (an object with
// "properties"; each property one type of boolean/string/number/integer/object/array; arrays with items of one of
// those but array; strings plain or base64), since a schema outside them makes the app drop the whole topic.
// Prints {topics: {topic: {encoding, schema, count}}, messages, errors: [...]} and exits 1 on any error.
import { readFile } from "node:fs/promises";
import { McapStreamReader } from "@mcap/core";
import { parse as parseRosmsg } from "@lichtblick/rosmsg";
import { MessageReader } from "@lichtblick/rosmsg2-serialization";
import protobufjs from "protobufjs";
import "protobufjs/ext/descriptor/index.js";

const SCALARS = new Set(["boolean", "string", "number", "integer"]);

function checkJsonSchema(schema, where) {
  if (schema.type !== "object") throw new Error(`${where}: "type" must be "object", not ${JSON.stringify(schema.type)}`);
  // Foxglove Studio up to 1.x reads Object.entries(schema.properties): an object without it fails the topic
  if (typeof schema.properties !== "object") throw new Error(`${where}: an object without "properties"`);
  for (const [name, prop] of Object.entries(schema.properties)) {
    const at = `${where}.${name}`;
    if (prop.oneOf !== undefined) throw new Error(`${at}: oneOf`);
    if (prop.type === "string" && ![undefined, "base64"].includes(prop.contentEncoding)) {
      throw new Error(`${at}: contentEncoding ${prop.contentEncoding}`);
    } else if (prop.type === "object") {
      checkJsonSchema(prop, at);
    } else if (prop.type === "array") {
      const item = prop.items?.type;
      if (!SCALARS.has(item) && item !== "object") throw new Error(`${at}[]: item type ${JSON.stringify(item)}`);
      if (item === "object") checkJsonSchema(prop.items, `${at}[]`);
    } else if (!SCALARS.has(prop.type)) {
      throw new Error(`${at}: type ${JSON.stringify(prop.type)}`);
    }
  }
}

function deserializer(channel, schema) {
  const text = new TextDecoder();
  switch (channel.messageEncoding) {
    case "json":
      if (schema && schema.encoding !== "jsonschema") throw new Error(`json with schema encoding ${schema.encoding}`);
      if (schema) checkJsonSchema(JSON.parse(text.decode(schema.data)), schema.name);
      return (data) => JSON.parse(text.decode(data));
    case "cdr": {
      if (schema?.encoding !== "ros2msg") throw new Error(`cdr with schema encoding ${schema?.encoding}`);
      const reader = new MessageReader(parseRosmsg(text.decode(schema.data), { ros2: true }));
      return (data) => reader.readMessage(data);
    }
    case "protobuf": {
      if (schema?.encoding !== "protobuf") throw new Error(`protobuf with schema encoding ${schema?.encoding}`);
      const descriptor = protobufjs.descriptor.FileDescriptorSet.decode(schema.data);
      const type = protobufjs.Root.fromDescriptor(descriptor, { keepCase: true }).lookupType(schema.name);
      return (data) => type.toObject(type.decode(data), { defaults: true });
    }
    default:
      throw new Error(`encoding ${JSON.stringify(channel.messageEncoding)} no viewer reads`);
  }
}

const file = process.argv[2];
const reader = new McapStreamReader({ validateCrcs: true });
reader.append(new Uint8Array(await readFile(file)));
const schemas = new Map(), decoders = new Map(), topics = {}, errors = [];
let messages = 0;
try {
  for (let rec; (rec = reader.nextRecord()) !== undefined; ) {
    if (rec.type === "Schema") schemas.set(rec.id, rec);
    else if (rec.type === "Channel") {
      if (decoders.has(rec.id)) continue; // a chunked file repeats its channels
      const schema = schemas.get(rec.schemaId);
      topics[rec.topic] ??= { encoding: rec.messageEncoding, schema: schema?.name ?? "", count: 0 };
      try {
        decoders.set(rec.id, { topic: rec.topic, decode: deserializer(rec, schema) });
      } catch (e) {
        decoders.set(rec.id, null); // the app drops the topic: its messages are not decoded
        errors.push(`${rec.topic}: ${e.message}`);
      }
    } else if (rec.type === "Message") {
      const d = decoders.get(rec.channelId);
      if (d == null) continue;
      try {
        d.decode(rec.data);
        topics[d.topic].count += 1;
        messages += 1;
      } catch (e) {
        errors.push(`${d.topic} #${rec.sequence}: ${e.message}`);
      }
    }
  }
} catch (e) {
  errors.push(`reading the file: ${e.message}`);
}
if (!reader.done()) errors.push("the file ends early");
console.log(JSON.stringify({ file, messages, topics, errors: errors.slice(0, 20), n_errors: errors.length }, null, 1));
process.exit(errors.length ? 1 : 0);
