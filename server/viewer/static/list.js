// The session list: every session with its stats, refreshed every few seconds.
import { formatAge, formatBytes, json, withToken } from "./api.js";

const REFRESH_MS = 5000;  // each refresh asks every session for its stats (a decode where a fold changed it)
const body = document.querySelector("#sessions tbody");
const status = document.getElementById("status");

function cell(text, cls) {
  const td = document.createElement("td");
  td.textContent = text ?? "–";
  if (cls) td.className = cls;
  return td;
}

function row(s) {
  const tr = document.createElement("tr");
  tr.dataset.id = s.id;
  const name = document.createElement("td");
  if (s.state === "unavailable") name.textContent = s.id;
  else name.append(Object.assign(document.createElement("a"), { href: `/sessions/${s.id}/view`, textContent: s.id }));
  name.className = "id";
  tr.append(name, cell(s.problem ? `${s.state}: ${s.problem}` : s.state, "state"), cell(s.frames, "frames"),
            cell(s.voxels, "voxels"), cell(s.gaussians, "gaussians"), cell(formatBytes(s.memory_bytes), "memory"),
            cell(formatAge(s.last_fold), "last-fold"));
  return tr;
}

async function refresh() {
  const { sessions } = await withToken(() => json("/v1/viewer/sessions"));
  body.replaceChildren(...sessions.map(row));
  document.getElementById("empty").hidden = sessions.length > 0;
  status.textContent = `${sessions.length} session${sessions.length === 1 ? "" : "s"}`;
}

async function loop() {
  try {
    await refresh();
  } catch (error) {
    status.textContent = `error: ${error.message}`;
  }
  setTimeout(loop, REFRESH_MS);
}

loop();
