// The omg4 export's page: one <omg4-player> (element.js) filling the window, pointed at what the export wrote
// (omg4-web.json lists it): model.omg4 — or, for a long capture, sequence.json — and cameras.json when the export
// had a dataset. URL parameters: ?camera=<name>&time=<T>&width=<W>&height=<H>&ui=0&background=r,g,b&model=<file> (a
// reproducible view: no camera → the first test camera, as `omg4 render --data` picks; a time → paused there; ui=0 →
// only the image, no controls). window.omg4Ready resolves after the first complete frame (rejects with the one-line
// message a damaged file gets, also shown in #message); window.omg4Player is the element.

import "./element.js";

const params = new URLSearchParams(location.search);
const player = document.querySelector("omg4-player");
let settle;
window.omg4Ready = new Promise((resolve, reject) => { settle = { resolve, reject }; });
window.omg4Ready.catch(() => {});
window.omg4Player = player;

function show(message) {
  const box = document.getElementById("message");
  box.textContent = message.split("\n")[0];
  box.hidden = false;
}

async function exportedFiles() {
  // what the export wrote, so the page asks for no file that is not there
  const response = await fetch("omg4-web.json", { cache: "no-store" });
  return new Set(response.ok ? (await response.json()).files : []);
}

async function main() {
  const bare = params.get("ui") === "0";
  if (bare) document.body.classList.add("bare");
  const files = await exportedFiles();
  const sequence = files.has("sequence.json") && params.get("model") === null;
  player.addEventListener("ready", (e) => {
    window.omg4FirstFrameMs = performance.now();  // since navigation started
    settle.resolve(e.detail);
  });
  player.addEventListener("error", (e) => {
    show(e.detail.message);
    document.body.dataset.error = e.detail.name;
    settle.reject(Object.assign(new Error(e.detail.message), { name: e.detail.name }));
  });
  for (const name of ["camera", "time", "width", "height", "background"]) {
    if (params.get(name) !== null) player.setAttribute(name, params.get(name));
  }
  if (files.has("cameras.json")) player.setAttribute("cameras", "cameras.json");
  player.toggleAttribute("controls", !bare);
  player.toggleAttribute("autoplay", params.get("time") === null);
  player.setAttribute("src", sequence ? "sequence.json" : params.get("model") ?? "model.omg4");
}

main().catch((err) => {
  show(err.message);
  document.body.dataset.error = err.name;
  settle.reject(err);
});
