// Opens a run's MCAP in Foxglove Studio (index.html, served by serve.mjs on PORT) in headless
// Chromium, seeks to the end of the run, saves a screenshot of the layout (3D panel, head camera)
// and lists the problems the viewer reports (a topic it cannot read, a frame it cannot place).
// Exit status 1 when it reports any. Usage: node shot.mjs PORT RUN.mcap OUT.png
import { chromium } from "playwright-core";
import { McapIndexedReader } from "@mcap/core";
import fs from "node:fs/promises";

const [port, mcapPath, out] = process.argv.slice(2);
// The topics the 3D panel shows: the scene, the estimates, tracking, maps and point clouds.
const fh = await fs.open(mcapPath, "r");
const size = (await fh.stat()).size;
const reader = await McapIndexedReader.Initialize({
  readable: {
    size: async () => BigInt(size),
    read: async (offset, length) => {
      const buf = new Uint8Array(Number(length));
      await fh.read(buf, 0, Number(length), Number(offset));
      return buf;
    },
  },
});
const all = [...reader.channelsById.values()].map((c) => c.topic);
// (The maps are left to the user: their unknown cells would cover the terrain.)
const topics = all.filter((t) => /^\/(scene|estimate|tracking)\//.test(t) || t.endsWith("/points"));
const image = all.includes("/sensors/head_stereo/left") ? "/sensors/head_stereo/left" : undefined;
await fh.close();

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
  // Software WebGL (SwiftShader) for the 3D panel; no network beyond loopback.
  args: ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-quic",
    "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"],
});
const page = await browser.newPage({ viewport: { width: 1600, height: 900 } });
const problems = [];
page.on("pageerror", (e) => problems.push(`page error: ${e}`));
page.on("console", (m) => {
  // A failed request is reported below with its address.
  if (m.type() === "error" && !m.text().startsWith("Failed to load resource")) {
    problems.push(m.text().split("\n")[0].slice(0, 300));
  }
});
page.on("response", (r) => {
  if (r.status() >= 400 && !r.url().endsWith("/favicon.ico")) problems.push(`HTTP ${r.status()}: ${r.url()}`);
});
await page.addInitScript(([t, i]) => { window.ROVER_TWIN_TOPICS = t; window.ROVER_TWIN_IMAGE = i; }, [topics, image]);
const url = encodeURIComponent(`http://127.0.0.1:${port}/run.mcap`);
// The server may still be starting.
for (let tries = 0; ; tries++) {
  try {
    await page.goto(`http://127.0.0.1:${port}/index.html?ds=remote-file&ds.url=${url}&layoutId=rover-twin`);
    break;
  } catch (e) {
    if (tries >= 20) throw e;
    await new Promise((r) => setTimeout(r, 250));
  }
}
const forward = page.locator('[title="Seek forward"]').first();
await forward.waitFor({ timeout: 60000 });
await page.waitForTimeout(5000);
// Close the data source sidebar and the settings hint, then seek to the end of the run (a click
// at the right end of the playback bar).
const sidebar = page.locator('[title="Data source"]').first();
if (await sidebar.count()) await sidebar.click();
const dismiss = page.locator('[aria-label="Dismiss"]').first();
if (await dismiss.count()) await dismiss.click();
// The bar is the 32 px row right above the playback time, across the window.
const time = await page.locator("[data-testid=PlaybackTime-text]").first().boundingBox();
if (!time) throw new Error("no playback controls found");
const bar = { x: 1600 - 10, y: time.y - 16 };
await page.mouse.click(bar.x, bar.y);
await page.mouse.move(800, 450);
await page.waitForTimeout(8000);
await page.screenshot({ path: out });
console.log(`${out}: ${topics.length} topics shown in 3D${image ? `, ${image}` : ""}`);
for (const p of problems) console.log(`viewer: ${p}`);
await browser.close();
process.exit(problems.length > 0 ? 1 : 0);
