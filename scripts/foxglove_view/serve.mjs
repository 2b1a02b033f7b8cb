// A static file server on loopback with HTTP Range support (Foxglove's remote-file source reads
// the MCAP in ranges): ROOT's files, and RUN.mcap as /run.mcap. Usage: node serve.mjs ROOT PORT RUN.mcap
import http from "node:http";
import fs from "node:fs";
import path from "node:path";
const [root, port, run] = process.argv.slice(2);
const types = { ".html": "text/html", ".js": "text/javascript", ".wasm": "application/wasm",
  ".png": "image/png", ".ttf": "font/ttf", ".mcap": "application/octet-stream" };
http.createServer((req, res) => {
  const rel = decodeURIComponent(new URL(req.url, "http://x").pathname);
  const file = rel === "/run.mcap" ? run : path.join(root, path.normalize(rel).replace(/^(\.\.[/\\])+/, ""));
  fs.stat(file, (err, st) => {
    if (err || !st.isFile()) { res.writeHead(404); res.end(); return; }
    const headers = { "Content-Type": types[path.extname(file)] ?? "application/octet-stream",
      "Accept-Ranges": "bytes", "Access-Control-Allow-Origin": "*",
      "Access-Control-Expose-Headers": "Accept-Ranges, Content-Range, Content-Length" };
    const m = /^bytes=(\d*)-(\d*)$/.exec(req.headers.range ?? "");
    if (m) {
      const start = m[1] === "" ? Math.max(0, st.size - Number(m[2])) : Number(m[1]);
      const end = m[1] !== "" && m[2] !== "" ? Math.min(Number(m[2]), st.size - 1) : st.size - 1;
      res.writeHead(206, { ...headers, "Content-Range": `bytes ${start}-${end}/${st.size}`,
        "Content-Length": end - start + 1 });
      if (req.method === "HEAD") { res.end(); return; }
      fs.createReadStream(file, { start, end }).pipe(res);
    } else {
      res.writeHead(200, { ...headers, "Content-Length": st.size });
      if (req.method === "HEAD") { res.end(); return; }
      fs.createReadStream(file).pipe(res);
    }
  });
}).listen(Number(port), "127.0.0.1");
