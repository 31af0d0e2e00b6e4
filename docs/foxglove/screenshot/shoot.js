// Screenshots of a run log (MCAP) in Foxglove Studio (@foxglove/studio-base 1.48.0 web bundle).
// Usage: node shoot.js OUTDIR [PREFIX]   (server must already serve web/ at $STUDIO_BASE)
// Env: STUDIO_BASE (default http://127.0.0.1:8765), CHROMIUM (default /usr/bin/chromium),
//      TIMES (comma list of seconds from log start, default "2,5,9.5"), WAIT_MS (load wait, default 15000)
const puppeteer = require("puppeteer-core");
const fs = require("fs");
const OUT = process.argv[2] || "/tmp/shots";
const PREFIX = process.argv[3] || "";
const BASE = process.env.STUDIO_BASE || "http://127.0.0.1:8765";
const TIMES = (process.env.TIMES || "2,5,9.5").split(",").map(Number);
const WAIT_MS = Number(process.env.WAIT_MS || 15000);
const PAGE = process.env.PAGE || "index.html";
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

function rfc3339(startNs, offsetS) {
  const ns = startNs + BigInt(Math.round(offsetS * 1e9));
  const sec = ns / 1000000000n, frac = (ns % 1000000000n).toString().padStart(9, "0");
  return new Date(Number(sec) * 1000).toISOString().replace(/\.\d{3}Z$/, `.${frac}Z`);
}

async function clickButtonByTitle(page, title) {
  return page.evaluate((t) => { const b = document.querySelector(`button[title="${t}"]`); if (b) { b.click(); return true; } return false; }, title);
}
async function dismissPopovers(page) {
  // the 3D panel's "Open settings to configure topics and layers." hint has a close (x) button
  await page.evaluate(() => {
    for (const el of document.querySelectorAll("div,p,span")) {
      if (el.childElementCount === 0 && /Open settings to configure/.test(el.textContent)) {
        let p = el; for (let i = 0; i < 5 && p; i++, p = p.parentElement) {
          const b = p.querySelector("button"); if (b) { b.click(); return; }
        }
      }
    }
  });
}

(async () => {
  fs.mkdirSync(OUT, { recursive: true });
  const startNs = BigInt(process.env.LOG_START_NS || "0");
  const browser = await puppeteer.launch({
    executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
    headless: true,
    args: ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
           "--window-size=1600,1000"],
    defaultViewport: { width: 1600, height: 1000 },
  });
  const logs = [];
  let first = true;
  for (const t of TIMES) {
    const page = await browser.newPage();
    page.on("console", (m) => logs.push(`[t=${t}] [${m.type()}] ${m.text()}`));
    page.on("pageerror", (e) => logs.push(`[t=${t}] [pageerror] ${e.message}`));
    const url = `${BASE}/${PAGE}?ds=remote-file&ds.url=${encodeURIComponent(BASE + "/data/run.mcap")}` +
      (startNs > 0n ? `&time=${rfc3339(startNs, t)}` : "");
    console.log("open", url);
    await page.goto(url, { waitUntil: "load", timeout: 180000 });
    await page.waitForFunction(() => /DURATION/i.test(document.body.innerText), { timeout: 120000 });
    await sleep(WAIT_MS);
    if (first) {
      // data-source sidebar with the Problems tab: the app's own list of channel errors
      await page.evaluate(() => { for (const tab of document.querySelectorAll('[role="tab"]')) if (/Problems/.test(tab.textContent)) tab.click(); });
      await sleep(1500);
      const problems = await page.evaluate(() => [...document.querySelectorAll("*")]
        .filter((e) => e.textContent.trim().startsWith("Error in topic") &&
          ![...e.children].some((c) => c.textContent.trim().startsWith("Error in topic")))
        .map((e) => e.textContent.replace(/\s+/g, " ").trim()).join("\n"));
      fs.writeFileSync(`${OUT}/${PREFIX}problems.txt`, problems + "\n");
      await page.screenshot({ path: `${OUT}/${PREFIX}00_sidebar_problems.png` });
      first = false;
    }
    await clickButtonByTitle(page, "Data source");  // collapse the left sidebar
    await dismissPopovers(page);
    await page.mouse.move(1599, 999);
    await sleep(3000);
    const name = `${OUT}/${PREFIX}t${String(t).replace(".", "_")}s.png`;
    await page.screenshot({ path: name });
    console.log("wrote", name);
    await page.close();
  }
  // Playback mode: a seek clears the Log panel (it then shows only the latest message), so for
  // screenshots with the log history, play from the start and pause at each PLAY_TIMES offset.
  const PLAY_TIMES = (process.env.PLAY_TIMES || "5,9.7").split(",").filter(Boolean).map(Number);
  if (PLAY_TIMES.length) {
    const page = await browser.newPage();
    page.on("console", (m) => logs.push(`[play] [${m.type()}] ${m.text()}`));
    page.on("pageerror", (e) => logs.push(`[play] [pageerror] ${e.message}`));
    await page.goto(`${BASE}/${PAGE}?ds=remote-file&ds.url=${encodeURIComponent(BASE + "/data/run.mcap")}`, { waitUntil: "load", timeout: 180000 });
    await page.waitForFunction(() => /DURATION/i.test(document.body.innerText), { timeout: 120000 });
    await sleep(WAIT_MS);
    await clickButtonByTitle(page, "Data source");
    await dismissPopovers(page);
    const now = () => page.evaluate(() => {  // the playback time display, as seconds of the day
      for (const el of document.querySelectorAll("input,div,span,p")) {
        const r = el.getBoundingClientRect(); if (r.top < window.innerHeight - 80) continue;
        const txt = el.tagName === "INPUT" ? el.value : (el.childElementCount === 0 ? el.textContent : "");
        const m = /(\d{1,2}):(\d\d):(\d\d(?:\.\d+)?)\s*(AM|PM)?/.exec(txt || ""); if (!m) continue;
        let hh = Number(m[1]) % 12 + (m[4] === "PM" ? 12 : 0); if (!m[4]) hh = Number(m[1]);
        return hh * 3600 + Number(m[2]) * 60 + Number(m[3]);
      }
      return null;
    });
    const t0 = await now();
    console.log("play: start time display (s of day)", t0);
    for (const target of PLAY_TIMES) {
      await clickButtonByTitle(page, "Play");
      const deadline = Date.now() + 60000;
      let cur = t0;
      while (Date.now() < deadline) { cur = await now(); if (cur != null && cur - t0 >= target) break; await sleep(30); }
      await clickButtonByTitle(page, "Pause");
      await page.mouse.move(1599, 999);
      await sleep(3000);
      const name = `${OUT}/${PREFIX}play_t${String(target).replace(".", "_")}s.png`;
      await page.screenshot({ path: name });
      console.log("wrote", name, "paused at offset", ((await now()) - t0).toFixed(3));
    }
    await page.close();
  }
  fs.writeFileSync(`${OUT}/${PREFIX}console.log`, logs.join("\n") + "\n");
  await browser.close();
})().catch((e) => { console.error(e); process.exit(1); });
