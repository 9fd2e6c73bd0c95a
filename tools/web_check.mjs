#!/usr/bin/env node
// Load a dars WebXR page (viewers/web.py) in headless Chromium, wait until it has drawn, and report.
// Usage: node tools/web_check.mjs URL --out SHOT.png [--width 320 --height 240] [--timeout 60000]
//        [--chromium /usr/bin/chromium]
// Prints JSON on stdout: {ready, error, console_errors: [...], page_errors: [...], warnings: [...], vr_button,
// xr_enabled, meshes, webgl}. Exit status 0 when the page became ready without console/page errors, 1 otherwise,
// 2 on bad usage or when the browser cannot start. Uses playwright-core (tools/package.json) with the system
// Chromium (Debian `chromium`); it never downloads a browser.
import { chromium } from 'playwright-core';
import fs from 'node:fs';
import os from 'node:os';
import path from 'node:path';

const args = process.argv.slice(2);
const opt = (name, dflt) => { const i = args.indexOf(`--${name}`); return i >= 0 ? args[i + 1] : dflt; };
const url = args[0];
if (!url || url.startsWith('--')) {
  console.error('usage: node tools/web_check.mjs URL --out SHOT.png [--width W --height H] [--timeout MS]');
  process.exit(2);
}
const out = opt('out', null);
const width = parseInt(opt('width', '320'), 10);
const height = parseInt(opt('height', '240'), 10);
const timeout = parseInt(opt('timeout', '60000'), 10);
const executablePath = opt('chromium', process.env.DARS_CHROMIUM || '/usr/bin/chromium');

const userDataDir = fs.mkdtempSync(path.join(os.tmpdir(), 'dars-chromium-'));
const flags = ['--no-sandbox', '--disable-gpu', '--disable-background-networking', '--disable-component-update',
  '--disable-sync', '--no-first-run', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
  '--ignore-gpu-blocklist'];
let browser;
const report = { ready: false, error: null, console_errors: [], page_errors: [], warnings: [], failed_requests: [] };
try {
  browser = await chromium.launchPersistentContext(userDataDir, {
    executablePath, headless: true, args: flags, viewport: { width, height }, deviceScaleFactor: 1,
  });
} catch (err) {
  console.error(`cannot start ${executablePath}: ${err.message}`);
  process.exit(2);
}
try {
  const page = browser.pages()[0] || await browser.newPage();
  page.on('console', (msg) => {
    if (msg.type() === 'error') report.console_errors.push(msg.text());
    else if (msg.type() === 'warning') report.warnings.push(msg.text());
  });
  page.on('pageerror', (err) => report.page_errors.push(String(err && err.message ? err.message : err)));
  page.on('requestfailed', (req) => report.failed_requests.push(`${req.url()}: ${req.failure()?.errorText}`));
  page.on('response', (res) => { if (res.status() >= 400) report.failed_requests.push(`${res.url()}: HTTP ${res.status()}`); });
  await page.goto(url, { waitUntil: 'load', timeout });
  try {
    await page.waitForFunction(() => window.__dars && (window.__dars.ready || window.__dars.error), null,
      { timeout, polling: 200 });
  } catch (err) {
    report.error = `page not ready after ${timeout} ms`;
  }
  const state = await page.evaluate(() => {
    const d = window.__dars || {};
    const canvas = document.querySelector('canvas');
    const gl = canvas ? (canvas.getContext('webgl2') || null) : null;
    const button = document.getElementById('VRButton') || [...document.querySelectorAll('a, button')]
      .find((e) => /VR|WEBXR/.test(e.textContent || ''));
    return { ready: !!d.ready, error: d.error || null, meshes: d.meshes || 0, xr_enabled: !!d.xr,
      vr_button: button ? button.textContent : null, canvas: canvas ? [canvas.width, canvas.height] : null,
      webgl: gl ? gl.getParameter(gl.VERSION) : null };
  });
  Object.assign(report, state, { error: state.error || report.error });
  if (out && state.canvas) {  // the canvas' own pixels (preserveDrawingBuffer), without the HTML overlays
    const dataUrl = await page.evaluate(() => document.querySelector('canvas').toDataURL('image/png'));
    fs.writeFileSync(out, Buffer.from(dataUrl.split(',')[1], 'base64'));
    report.screenshot = out;
  }
} finally {
  await browser.close();
  fs.rmSync(userDataDir, { recursive: true, force: true });
}
process.stdout.write(JSON.stringify(report) + '\n');
process.exit(report.ready && !report.console_errors.length && !report.page_errors.length ? 0 : 1);
