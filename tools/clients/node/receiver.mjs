// Minimal Node.js receiver for the mocapd WebSocket pose stream (protocol: docs/streaming.md, "WebSocket").
//
//   npm ci                       # once, in this folder (ws + @msgpack/msgpack from package-lock.json)
//   node receiver.mjs [--url ws://127.0.0.1:8766/] [--frames N] [--convention unity] [--rate 30] [--token T]
//
// Prints the hello's skeleton summary, then one line per frame with each subject's root position, and exits 0
// after --frames frames (0 = run until Ctrl-C). Exits 1 if the stream ends first or sends an error.
import WebSocket from "ws";
import { decode } from "@msgpack/msgpack";

function option(name, fallback) {
  const i = process.argv.indexOf(`--${name}`);
  return i >= 0 && i + 1 < process.argv.length ? process.argv[i + 1] : fallback;
}

const url = new URL(option("url", "ws://127.0.0.1:8766/"));
const token = option("token", process.env.MOCAPD_TOKEN || "");
if (token) url.searchParams.set("token", token);
const wanted = Number(option("frames", "0"));
const subscribe = { type: "subscribe", convention: option("convention", "native") };
const rate = option("rate", null);
if (rate !== null) subscribe.rate_hz = Number(rate);

// Binary messages are msgpack, text messages JSON (the server answers in the encoding the client asked for).
const parse = (data, isBinary) => (isBinary ? decode(data) : JSON.parse(data.toString("utf8")));

const ws = new WebSocket(url);
let frames = 0;
let done = false;

ws.on("open", () => ws.send(JSON.stringify(subscribe)));
ws.on("message", (data, isBinary) => {
  if (done) return;  // messages already on their way while we close
  const m = parse(data, isBinary);
  if (m.type === "hello") {
    const names = Object.keys(m.skeletons);
    console.log(`hello v${m.v}: convention ${m.convention} (${m.units}), ${m.rate_hz} Hz, ` +
                `${m.bones.length} bones, skeletons ${names.join(",")}`);
  } else if (m.type === "frame") {
    frames += 1;
    const subjects = m.subjects.map((s) => `${s.id} root (${s.root.map((v) => v.toFixed(3)).join(", ")})`);
    console.log(`frame ${m.frame} t_solve_ns ${m.t_solve_ns}: ${subjects.join("; ") || "no subjects"}`);
    if (wanted > 0 && frames >= wanted) {
      done = true;
      ws.close(1000, "enough frames");
    }
  } else if (m.type === "status") {
    const o = m.output || {};
    console.log(`status: ${o.achieved_hz} Hz, ${o.missed_ticks} missed ticks, dropped ${m.stream.dropped}`);
  } else if (m.type === "error") {
    console.error(`error from server: ${m.code}: ${m.message}`);
    process.exitCode = 1;
  }
});
ws.on("close", () => {
  if (!done && wanted > 0) {
    console.error(`stream closed after ${frames} of ${wanted} frames`);
    process.exitCode = 1;
  }
});
ws.on("error", (err) => {
  console.error(`connection failed: ${err.message}`);
  process.exitCode = 1;
});
