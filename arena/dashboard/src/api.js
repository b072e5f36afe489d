// Arena's public REST and WebSocket API, as the dashboard uses it. Nothing here is private:
// the page works with exactly what any other client may call.

const KEY_STORAGE = "arena.apiKey";

/** An error answer of the server: `code` is machine-readable, `message` a plain sentence. */
export class ApiError extends Error {
  constructor(code, message, status) {
    super(message);
    this.code = code;
    this.status = status;
  }
}

export function apiKey() {
  return localStorage.getItem(KEY_STORAGE) || "";
}

export function setApiKey(key) {
  if (key) localStorage.setItem(KEY_STORAGE, key);
  else localStorage.removeItem(KEY_STORAGE);
}

/** Call the REST API; resolves to the decoded JSON, rejects with an ApiError. */
export async function call(method, path, body) {
  const headers = {};
  const key = apiKey();
  if (key) headers.Authorization = `Bearer ${key}`;
  if (body !== undefined) headers["Content-Type"] = "application/json";
  let response;
  try {
    response = await fetch(path, {
      method,
      headers,
      body: body === undefined ? undefined : JSON.stringify(body),
    });
  } catch (error) {
    throw new ApiError("UNREACHABLE", `The server cannot be reached (${error.message}).`, 0);
  }
  const text = await response.text();
  let data = null;
  try {
    data = text ? JSON.parse(text) : null;
  } catch {
    data = null;
  }
  if (!response.ok) {
    const error = data && data.error ? data.error : {};
    throw new ApiError(
      error.code || `HTTP_${response.status}`,
      error.message || `The server answered ${response.status}.`,
      response.status,
    );
  }
  return data;
}

/**
 * Call the REST API for something a person clicked: the answer, or null once the error went to
 * `report(text, true)` (pages show errors, they do not throw them).
 */
export async function callReporting(report, method, path, body) {
  try {
    return await call(method, path, body);
  } catch (error) {
    report(`${error.code}: ${error.message}`, true);
    return null;
  }
}

/** Fetch a file (a URDF, a mesh) with the API key, as a Response that is known to be ok. */
async function fetchFile(path) {
  const key = apiKey();
  const response = await fetch(path, { headers: key ? { Authorization: `Bearer ${key}` } : {} });
  if (!response.ok) {
    throw new ApiError(`HTTP_${response.status}`, `Cannot load ${path}.`, response.status);
  }
  return response;
}

export async function fetchBytes(path) {
  return (await fetchFile(path)).arrayBuffer();
}

export async function fetchText(path) {
  return (await fetchFile(path)).text();
}

/** A URL to download with the key (browsers cannot set headers on a plain link). */
export async function download(path, filename) {
  const bytes = await fetchBytes(path);
  const url = URL.createObjectURL(new Blob([bytes]));
  const link = document.createElement("a");
  link.href = url;
  link.download = filename;
  link.click();
  setTimeout(() => URL.revokeObjectURL(url), 1000);
}

// Close codes after which reconnecting cannot help.
const FINAL_CLOSES = { 4401: "API key needed", 4403: "key refused", 4404: "robot gone" };

/**
 * Watch one robot over `/ws/robots/{id}/state`: `onMessage(type, data)` for every `state` and
 * `joint_states`, `onStatus(text)` for the connection. Reconnects with backoff until closed.
 */
export function watchRobot(robotId, onMessage, onStatus) {
  let socket = null;
  let closed = false;
  let delay = 500;
  let timer = null;

  function connect() {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    const key = apiKey();
    const query = key ? `?token=${encodeURIComponent(key)}` : "";
    socket = new WebSocket(
      `${scheme}://${location.host}/ws/robots/${encodeURIComponent(robotId)}/state${query}`,
    );
    onStatus("connecting");
    socket.onopen = () => {
      delay = 500;
      onStatus("connected");
    };
    socket.onmessage = (event) => {
      let message;
      try {
        message = JSON.parse(event.data);
      } catch {
        return;
      }
      onMessage(message.type, message.data);
    };
    socket.onclose = (event) => {
      clearInterval(heartbeat);
      if (closed) return;
      const final = FINAL_CLOSES[event.code] || (event.reason === "robot deleted" && "robot deleted");
      if (final) {
        onStatus(final);
        return;
      }
      onStatus("disconnected, retrying");
      timer = setTimeout(connect, delay);
      delay = Math.min(delay * 2, 10000);
    };
    // Viewers are not dropped when silent, but a heartbeat keeps proxies from closing the socket.
    const heartbeat = setInterval(() => {
      if (socket.readyState === WebSocket.OPEN) socket.send('{"type":"heartbeat"}');
    }, 30000);
  }

  connect();
  return {
    close() {
      closed = true;
      clearTimeout(timer);
      if (socket) socket.close(1000);
    },
  };
}
