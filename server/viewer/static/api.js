// Data requests of the viewer pages: the bearer token (asked for once per tab, kept in
// sessionStorage, sent as an Authorization header, never in a URL) and the fold-event stream.

const TOKEN_KEY = "canonical.token";

export class Unauthorized extends Error {}

export function token() {
  return sessionStorage.getItem(TOKEN_KEY);
}

export function setToken(value) {
  if (value) sessionStorage.setItem(TOKEN_KEY, value);
  else sessionStorage.removeItem(TOKEN_KEY);
}

function headers(extra = {}) {
  const t = token();
  return t ? { ...extra, Authorization: `Bearer ${t}` } : extra;
}

// fetch with the token; throws Unauthorized on 401 and an Error naming the API's message otherwise.
export async function request(path, options = {}) {
  const response = await fetch(path, { ...options, headers: headers(options.headers) });
  if (response.status === 401) throw new Unauthorized("token required");
  if (!response.ok) {
    let message = `${response.status}`;
    try {
      const body = await response.json();
      // the service's messages begin with the field they name; the few that do not get it in front
      const { field, message: said } = body.error ?? {};
      if (said) message = !field || said.startsWith(`${field}:`) ? said : `${field}: ${said}`;
    } catch (_) { /* not JSON */ }
    const error = new Error(message);
    error.status = response.status;
    throw error;
  }
  return response;
}

export async function json(path, options) {
  return (await request(path, options)).json();
}

function tokenForm() {
  let form = document.getElementById("token-form");
  if (form) return form;
  form = Object.assign(document.createElement("form"), { id: "token-form", className: "token", hidden: true });
  const label = Object.assign(document.createElement("label"), { textContent: "This service needs its API token " });
  label.append(Object.assign(document.createElement("input"),
                             { type: "password", name: "token", autocomplete: "off", placeholder: "token" }));
  form.append(label, Object.assign(document.createElement("button"), { type: "submit", textContent: "Use token" }));
  document.body.append(form);
  return form;
}

// Show the token form and resolve once the user submitted a token; ``refused``: the token the tab
// held was turned down (a wrong one, or one the service no longer takes), which the form says.
export function askToken(refused = false) {
  const form = tokenForm();
  form.querySelector("label").firstChild.textContent = refused
    ? "The service refused that token: its API token " : "This service needs its API token ";
  form.querySelector("input").value = "";
  form.hidden = false;
  form.querySelector("input").focus();
  return new Promise((resolve) => {
    form.onsubmit = (event) => {
      event.preventDefault();
      setToken(form.querySelector("input").value.trim());
      form.hidden = true;
      resolve();
    };
  });
}

// Run fn(); when the service wants a token, ask for it and run fn again.
export async function withToken(fn) {
  for (;;) {
    try {
      return await fn();
    } catch (error) {
      if (!(error instanceof Unauthorized)) throw error;
      const refused = token() !== null;
      setToken(null);
      await askToken(refused);
    }
  }
}

// Download a session export through fetch (the token is a header, so a plain link cannot carry it).
export async function download(path, filename) {
  const blob = await (await request(path)).blob();
  const url = URL.createObjectURL(blob);
  const a = Object.assign(document.createElement("a"), { href: url, download: filename });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// Server-Sent Events read through fetch (EventSource cannot send an Authorization header).
// Calls onEvent(name, data) per event and reconnects after a dropped stream; returns a stop function.
export function subscribe(path, onEvent, onStatus = () => {}) {
  const controller = new AbortController();
  let stopped = false;
  async function run() {
    while (!stopped) {
      try {
        const response = await request(path, { signal: controller.signal, headers: { Accept: "text/event-stream" } });
        onStatus("live");
        const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
        let buffer = "";
        for (;;) {
          const { value, done } = await reader.read();
          if (done) break;
          buffer += value;
          let cut;
          while ((cut = buffer.indexOf("\n\n")) >= 0) {
            const block = buffer.slice(0, cut);
            buffer = buffer.slice(cut + 2);
            let name = "message";
            const data = [];
            for (const line of block.split("\n")) {
              if (line.startsWith("event:")) name = line.slice(6).trim();
              else if (line.startsWith("data:")) data.push(line.slice(5).trim());
            }
            if (data.length) onEvent(name, JSON.parse(data.join("\n")));
          }
        }
      } catch (error) {
        if (stopped) return;
        if (error instanceof Unauthorized) {  // a token set or changed since the page opened: ask again
          onStatus("unauthorized");
          const refused = token() !== null;
          setToken(null);
          await askToken(refused);
          continue;
        }
        if (error.status === 404) { onStatus("gone"); return; }
      }
      if (stopped) return;
      onStatus("reconnecting");
      await new Promise((r) => setTimeout(r, 1000));
    }
  }
  run();
  return () => { stopped = true; controller.abort(); };
}

export function formatBytes(n) {
  if (n == null) return "–";
  const units = ["B", "KiB", "MiB", "GiB"];
  let i = 0;
  while (n >= 1024 && i < units.length - 1) { n /= 1024; i += 1; }
  return `${n.toFixed(i ? 1 : 0)} ${units[i]}`;
}

export function formatAge(unixSeconds) {
  if (unixSeconds == null) return "–";
  const s = Math.max(0, Date.now() / 1000 - unixSeconds);
  if (s < 60) return `${s.toFixed(0)} s ago`;
  if (s < 3600) return `${(s / 60).toFixed(0)} min ago`;
  if (s < 86400) return `${(s / 3600).toFixed(1)} h ago`;
  return new Date(unixSeconds * 1000).toLocaleString();
}
