// A PNG of TensorBoard's time-series page, for a report or docs/img (headless Chromium).
// Set up once: apt-get install chromium; npm install --prefix /tmp/shot puppeteer-core@23
// Use: tensorboard --logdir RUN_DIR/tb --host 127.0.0.1 --port 6123 &
//      NODE_PATH=/tmp/shot/node_modules node tools/tensorboard-screenshot.js \
//        "http://127.0.0.1:6123/?tagFilter=eval%2Fsuccess#timeseries" OUT.png
const puppeteer = require("puppeteer-core");

(async () => {
  const [url, out] = process.argv.slice(2);
  const browser = await puppeteer.launch({
    executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
    headless: true,
    // The charts draw with WebGL; SwiftShader renders it without a GPU.
    args: ["--no-sandbox", "--use-gl=swiftshader", "--enable-unsafe-swiftshader"],
  });
  const page = await browser.newPage();
  await page.setViewport({ width: 1600, height: 1200 });
  await page.goto(url, { waitUntil: "networkidle0", timeout: 60000 });
  await new Promise((r) => setTimeout(r, 4000)); // cards load lazily after the page settles
  const close = await page.$('button[aria-label="Close side pane"]');
  if (close) {
    await close.click(); // the settings pane would take a third of the width
    await new Promise((r) => setTimeout(r, 3000));
  }
  await page.screenshot({ path: out });
  await browser.close();
})();
