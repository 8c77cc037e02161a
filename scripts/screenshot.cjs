// Screenshot of a page in headless Chromium (playwright-core), for the README images.
//
//   NODE_PATH=<folder holding playwright-core> node scripts/screenshot.cjs URL OUT.png [WAIT_S] [WIDTHxHEIGHT] [UNTIL]
//
// Waits WAIT_S seconds (default 10) for the page to load and draw, or, given UNTIL, until the page shows that
// text (at most WAIT_S seconds, then 3 more for the drawing to settle); removes viser's "software WebGL" notice
// (headless Chromium renders WebGL on the CPU), then saves the screenshot.
const { chromium } = require("playwright-core");
const fs = require("fs");
const os = require("os");
const path = require("path");

async function main() {
  const [url, out, waitS = "10", size = "1600x1000", until] = process.argv.slice(2);
  if (!url || !out) throw new Error("usage: node scripts/screenshot.cjs URL OUT.png [WAIT_S] [WIDTHxHEIGHT] [UNTIL]");
  const [width, height] = size.split("x").map(Number);
  const profile = fs.mkdtempSync(path.join(os.tmpdir(), "fdmo-chromium-"));
  const browser = await chromium.launchPersistentContext(profile, {
    executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
    headless: true,
    viewport: { width, height },
    args: ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
           "--no-first-run", "--enable-unsafe-swiftshader"],
  });
  try {
    const page = browser.pages()[0] || (await browser.newPage());
    await page.goto(url);
    if (until) {
      await page.getByText(until).first().waitFor({ timeout: 1000 * Number(waitS) });
      await page.waitForTimeout(3000);
    } else {
      await page.waitForTimeout(1000 * Number(waitS));
    }
    await page.evaluate(() => document.querySelectorAll(".mantine-Notification-root").forEach((n) => n.remove()));
    await page.waitForTimeout(500);
    await page.screenshot({ path: out });
  } finally {
    await browser.close();
    fs.rmSync(profile, { recursive: true, force: true });
  }
}

main().catch((error) => {
  console.error(error.message);
  process.exit(1);
});
