// The README's viewer screenshot: a page of a headless Chromium, captured through the DevTools protocol once the
// Rerun web viewer has drawn (Chromium's own --screenshot fires before the WebAssembly app renders). Everything
// stays on 127.0.0.1:
//
//   lego_loam_py run bags/campus_8s --viewer-save campus.rrd
//   rerun --serve-web --bind 127.0.0.1 --web-viewer-port 19090 --port 19876 campus.rrd &
//   chromium --headless --no-sandbox --disable-background-networking --disable-component-update --disable-sync \
//       --no-first-run --user-data-dir=$(mktemp -d) --enable-unsafe-swiftshader --use-angle=swiftshader \
//       --use-gl=angle --remote-debugging-address=127.0.0.1 --remote-debugging-port=19222 about:blank &
//   node --experimental-websocket docs/viewer_screenshot.js 19222 \
//       'http://127.0.0.1:19090/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A19876%2Fproxy&renderer=webgl' shot.png 45000
//
// (--disable-gpu leaves the viewer's canvas blank: WebGL then has no context; SwiftShader draws it on the CPU.)
const [port, url, out, waitMs] = process.argv.slice(2);
const fs = require('fs');
(async () => {
  const target = await (await fetch(`http://127.0.0.1:${port}/json/new?${encodeURIComponent(url)}`, {method: 'PUT'})).json();
  const ws = new WebSocket(target.webSocketDebuggerUrl);
  let id = 0; const pending = {};
  const send = (method, params = {}) => new Promise(r => { const i = ++id; pending[i] = r; ws.send(JSON.stringify({id: i, method, params})); });
  ws.onmessage = e => { const m = JSON.parse(e.data); if (m.id && pending[m.id]) pending[m.id](m); if (m.method === 'Runtime.consoleAPICalled') console.log('console:', JSON.stringify(m.params.args.map(a => a.value)).slice(0, 300)); };
  await new Promise(r => ws.onopen = r);
  await send('Runtime.enable');
  await send('Emulation.setDeviceMetricsOverride', {width: 1600, height: 900, deviceScaleFactor: 1, mobile: false});
  await new Promise(r => setTimeout(r, Number(waitMs)));
  const shot = await send('Page.captureScreenshot', {format: 'png'});
  fs.writeFileSync(out, Buffer.from(shot.result.data, 'base64'));
  console.log('wrote', out);
  ws.close(); process.exit(0);
})();
