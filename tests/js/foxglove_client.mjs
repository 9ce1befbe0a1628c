// A Foxglove WebSocket client built on @foxglove/ws-protocol (the client library of the Foxglove apps that speak
// "foxglove.websocket.v1"), as tests/clients/test_foxglove.py runs it against the bridge:
//   node foxglove_client.mjs ws://127.0.0.1:PORT SUBPROTOCOL TOPIC N
// connects offering SUBPROTOCOL, subscribes to TOPIC, and prints one JSON line: the server's name, capabilities
// and the first N messages of TOPIC decoded; or {"error": ...} (an HTTP 400 refusal of the handshake included).
import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

const { FoxgloveClient } = wsProtocol; // a CommonJS module

const [url, subprotocol, topic, n] = process.argv.slice(2);
const out = { subprotocol, messages: [] };
const done = (extra) => {
  console.log(JSON.stringify({ ...out, ...extra }));
  process.exit(0);
};
setTimeout(() => done({ error: "timed out" }), 10000);
const ws = new WebSocket(url, [subprotocol]);
ws.on("unexpected-response", (_req, res) => done({ error: `HTTP ${res.statusCode}` }));
ws.on("error", (e) => done({ error: String(e.message || e) }));
const client = new FoxgloveClient({ ws });
let sub = null;
client.on("serverInfo", (info) => {
  out.name = info.name;
  out.capabilities = info.capabilities;
});
client.on("advertise", (channels) => {
  for (const ch of channels) {
    if (ch.topic === topic && sub === null) {
      sub = client.subscribe(ch.id);
      out.schemaName = ch.schemaName;
    }
  }
});
client.on("message", (ev) => {
  if (ev.subscriptionId !== sub) return;
  out.messages.push(JSON.parse(new TextDecoder().decode(ev.data)));
  if (out.messages.length >= Number(n)) done({});
});
