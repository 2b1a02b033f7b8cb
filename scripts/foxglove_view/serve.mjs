// A static file server on loopback with HTTP Range support (Foxglove's remote-file source reads
// the MCAP in ranges): ROOT's files, and RUN.mcap as /run.mcap. Listens on a free port and writes
// it to PORT_FILE. Usage: node serve.mjs ROOT RUN.mcap PORT_FILE
import http from "node:http";
import fs from "node:fs";
import path from "node:path";
const [root, run, portFile] = process.argv.slice(2);
const types = { ".html": "text/html", ".js": "text/javascript", ".wasm": "application/wasm",
  ".png": "image/png", ".ttf": "font/ttf", ".mcap": "application/octet-stream" };
function serve(req, res) {
  const rel = decodeURIComponent(new URL(req.url, "http://x").pathname);
  // normalize() of an absolute path resolves every "..": the file stays under ROOT.
  const file = rel === "/run.mcap" ? run : path.join(root, path.normalize(rel));
  const st = fs.statSync(file, { throwIfNoEntry: false });
  if (!st || !st.isFile()) { res.writeHead(404); res.end(); return; }
  const headers = { "Content-Type": types[path.extname(file)] ?? "application/octet-stream",
    "Accept-Ranges": "bytes", "Access-Control-Allow-Origin": "*",
    "Access-Control-Expose-Headers": "Accept-Ranges, Content-Range, Content-Length" };
  const range = req.headers.range;
  let start = 0, end = st.size - 1, status = 200;
  if (range !== undefined) {
    const m = /^bytes=(\d*)-(\d*)$/.exec(range);
    if (m && m[1] !== "") { start = Number(m[1]); if (m[2] !== "") end = Math.min(Number(m[2]), st.size - 1); }
    else if (m && m[2] !== "") start = Math.max(0, st.size - Number(m[2]));
    if (!m || (m[1] === "" && m[2] === "") || start > end || start >= st.size) {
      res.writeHead(416, { ...headers, "Content-Range": `bytes */${st.size}` }); res.end(); return;
    }
    status = 206;
    headers["Content-Range"] = `bytes ${start}-${end}/${st.size}`;
  }
  res.writeHead(status, { ...headers, "Content-Length": end - start + 1 });
  if (req.method === "HEAD" || st.size === 0) { res.end(); return; }
  fs.createReadStream(file, { start, end }).on("error", () => res.destroy()).pipe(res);
}
const server = http.createServer((req, res) => {
  try { serve(req, res); } catch { if (!res.headersSent) res.writeHead(400); res.end(); }
});
server.listen(0, "127.0.0.1", () => fs.writeFileSync(portFile, String(server.address().port)));
