// The console end to end in Debian's headless Chromium, as an operator and an observer use it, against a simulated
// stage that tests/console_test.cc started with a console in front of it. Prints one JSON line of what it measured;
// exits non-zero, saying why, at the first thing that is not as it should be.
//
// Environment: CONSOLE_URL, OPERATOR (name:password), OBSERVER (name:password), VICTIM_ID and VICTIM_PID (the camera
// node to kill), SCREENSHOTS (a directory for a PNG of each page), TAKE_SECONDS.
import { chromium } from 'playwright-core';
import { mkdirSync } from 'node:fs';

const env = (name) => {
  if (!process.env[name]) throw new Error(`${name} is not set`);
  return process.env[name];
};
const url = env('CONSOLE_URL');
const [operator, operatorPassword] = env('OPERATOR').split(':');
const [observer, observerPassword] = env('OBSERVER').split(':');
const shots = env('SCREENSHOTS');
mkdirSync(shots, { recursive: true });
const measured = {};

function check(condition, what) {
  if (!condition) throw new Error(what);
}

async function login(page, user, password) {
  await page.goto(url);
  await page.waitForSelector('#login-form', { state: 'visible' });
  await page.fill('#login-user', user);
  await page.fill('#login-password', password);
  await page.click('#login-submit');
  await page.waitForSelector('#pages', { state: 'visible' });
}

async function shot(page, name) {
  await page.screenshot({ path: `${shots}/${name}.png`, fullPage: false });
}

const browser = await chromium.launch({ executablePath: '/usr/bin/chromium', args: ['--no-sandbox'] });
try {
  const context = await browser.newContext({ viewport: { width: 1400, height: 900 } });
  const page = await context.newPage();
  page.on('dialog', (d) => d.accept());
  const pageErrors = [];
  page.on('pageerror', (e) => pageErrors.push(e.message));

  // A wrong password is refused, and says so.
  await page.goto(url);
  await page.waitForSelector('#login-form', { state: 'visible' });
  await page.fill('#login-user', operator);
  await page.fill('#login-password', 'not the password');
  await page.click('#login-submit');
  await page.waitForFunction(() => document.getElementById('login-error').textContent.length > 0);
  check((await page.textContent('#login-error')).includes('wrong password'), 'a wrong password was not refused');
  await shot(page, 'login');

  // 1. Every node up.
  await login(page, operator, operatorPassword);
  await page.waitForFunction(() => {
    const cards = document.querySelectorAll('#nodes .card');
    return cards.length > 0 && [...cards].every((c) => c.dataset.link === 'up') &&
      document.querySelectorAll('#nodes .card .device:not(:empty)').length > 0;
  }, null, { timeout: 60000 });
  measured.nodes = await page.locator('#nodes .card').count();
  await shot(page, 'stage');

  // 2. A take: armed, captured, the ledger grid filling to COMPLETE.
  await page.click('nav a[href="#/take"]');
  await page.fill('#take-seconds', process.env.TAKE_SECONDS || '1');
  await page.fill('#take-name', 'console e2e');
  await page.click('#cmd-arm');
  await page.waitForFunction(() => document.getElementById('session').dataset.state === 'ARMED', null,
    { timeout: 120000 });
  await page.click('#cmd-capture');
  // While it records, the grid has a row per camera, cells filling.
  await page.waitForFunction(() => document.querySelectorAll('#ledger .row').length > 0, null, { timeout: 120000 });
  await shot(page, 'take-recording');
  await page.waitForFunction(() => document.getElementById('take-outcome').dataset.outcome !== undefined &&
    document.getElementById('ledger').dataset.complete === 'true', null, { timeout: 600000 });
  measured.outcome = await page.getAttribute('#take-outcome', 'data-outcome');
  check(measured.outcome === 'COMPLETE', `the take ended ${measured.outcome}: ${await page.textContent('#take-outcome')}`);
  measured.ledger_rows = await page.locator('#ledger .row').count();
  measured.lost_cells = await page.locator('#ledger .cell.lost').count();
  check(measured.lost_cells === 0, `${measured.lost_cells} lost cells in a COMPLETE take`);
  await shot(page, 'take');

  // 3. A preview of a camera: drawn, stretched, with its histogram and a pixel's value.
  await page.click('nav a[href="#/previews"]');
  await page.waitForFunction(() => document.getElementById('preview-canvas').dataset.loaded, null, { timeout: 30000 });
  const box = await page.locator('#preview-canvas').boundingBox();
  await page.mouse.move(box.x + box.width / 2, box.y + box.height / 2);
  check((await page.textContent('#preview-pixel')).includes('R '), 'no pixel value under the cursor');
  check((await page.textContent('#preview-stretch')).startsWith('stretched'), 'the preview was not stretched');
  await shot(page, 'previews');

  // 4. The timing of one frame, drawn.
  await page.click('nav a[href="#/timing"]');
  await page.waitForFunction(() => {
    const img = document.querySelector('#timing-waveform img');
    return img && img.complete && img.naturalWidth > 0;
  }, null, { timeout: 30000 });
  await shot(page, 'timing');

  // 5. The take in the catalog.
  await page.click('nav a[href="#/takes"]');
  await page.waitForSelector('#takes-table tbody tr');
  await page.click('#takes-table tbody tr:first-child a');
  await page.waitForFunction(() => document.querySelector('#takes-table tbody tr:first-child .selftest').textContent);
  await shot(page, 'takes');

  // 6. An observer: sees the stage, may not command it, may press the emergency stop.
  const observerPage = await (await browser.newContext({ viewport: { width: 1400, height: 900 } })).newPage();
  observerPage.on('dialog', (d) => d.accept());
  await login(observerPage, observer, observerPassword);
  await observerPage.click('nav a[href="#/take"]');
  check(await observerPage.isDisabled('#cmd-capture'), "an observer's Capture button is enabled");
  const refused = await observerPage.evaluate(async () => (await fetch('/api/abort', { method: 'POST',
    headers: { 'X-FaStage': '1' } })).status);
  check(refused === 403, `an observer's abort answered ${refused}, not 403`);

  // 7. The emergency stop, one click from the page the observer is on: every light node dark.
  await observerPage.click('#estop');
  await page.click('nav a[href="#/stage"]');
  await page.waitForFunction(() => {
    const lights = [...document.querySelectorAll('#nodes .card')].filter((c) => c.querySelector('small').textContent === 'light');
    return document.body.dataset.estop === 'latched' && lights.length > 0 && lights.every((c) => c.dataset.light === 'dark');
  }, null, { timeout: 10000 });
  measured.lights_dark = await page.locator('#nodes .card[data-light="dark"]').count();
  await shot(page, 'estop');

  // 8. A camera node killed: red within a second.
  const victim = env('VICTIM_ID');
  const killedAt = Date.now();
  process.kill(Number(env('VICTIM_PID')), 'SIGKILL');
  await page.waitForFunction((id) => {
    const card = document.querySelector(`#nodes .card[data-node="${id}"]`);
    return card && card.dataset.link !== 'up';
  }, victim, { timeout: 10000, polling: 10 });
  measured.red_after_ms = Date.now() - killedAt;
  check(measured.red_after_ms < 1000, `${victim} went red after ${measured.red_after_ms} ms, not within 1 s`);
  await shot(page, 'node-down');

  // 9. Its alarm, acknowledged by the operator.
  await page.click('nav a[href="#/alarms"]');
  const row = `#alarms-active tr[data-key="node-down:${victim}"]`;
  await page.waitForSelector(`${row} button[data-ack]`, { timeout: 10000 });
  await page.click(`${row} button[data-ack]`);
  await page.waitForFunction((sel) => document.querySelector(sel)?.classList.contains('acked'), row,
    { timeout: 60000 });
  await shot(page, 'alarms');

  // 10. The log tail.
  await page.click('nav a[href="#/log"]');
  await page.waitForFunction(() => document.getElementById('log-lines').textContent.length > 0);
  await shot(page, 'log');
  check(pageErrors.length === 0, `errors in the page: ${pageErrors.join('; ')}`);
  console.log(JSON.stringify(measured));
} catch (e) {
  // What the page said when it went wrong, and what it looked like.
  for (const p of browser.contexts().flatMap((c) => c.pages())) {
    const said = await p.evaluate(() => ['toast', 'preview-info', 'take-outcome', 'take-progress', 'link']
      .map((id) => `#${id}: ${document.getElementById(id)?.textContent}`).join('\n')).catch(() => '');
    console.error(`at ${p.url()}:\n${said}`);
    await p.screenshot({ path: `${shots}/failure-${browser.contexts().indexOf(p.context())}.png` }).catch(() => {});
  }
  throw e;
} finally {
  await browser.close();
}
