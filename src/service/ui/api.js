// The HTTP client of the page: every request the page makes to the service goes through here.
// It owns the API key (kept in localStorage, sent as `Authorization: Bearer …` when the server
// runs with --api-key) and turns a non-2xx answer into an `ApiError` carrying the problem+json
// `code`, `detail`, `field` and Retry-After, which app.js shows. It never touches the document:
// the callers decide what to show. The event stream is read with fetch and a streaming reader,
// parsed here, since EventSource cannot send an Authorization header. `fetchPublic` is the one
// request without the key (the server's public files: the viewer's shader include).

const KEY_STORAGE = 'horizon-bake.api-key';

export function getApiKey() {
  try {
    return localStorage.getItem(KEY_STORAGE) || '';
  } catch {
    return '';
  }
}

export function setApiKey(key) {
  try {
    if (key) localStorage.setItem(KEY_STORAGE, key);
    else localStorage.removeItem(KEY_STORAGE);
  } catch {
    // Storage can be disabled (private mode): the key then lives only in the field.
  }
}

/** An HTTP answer that was not 2xx, with the problem+json fields when the body had them. */
export class ApiError extends Error {
  constructor(status, problem, retryAfter) {
    const detail = (problem && problem.detail) || `HTTP ${status}`;
    super(detail);
    this.status = status;
    this.code = (problem && problem.code) || `http_${status}`;
    this.detail = detail;
    this.field = (problem && problem.field) || null;
    this.title = (problem && problem.title) || '';
    this.retryAfter = retryAfter;
  }
}

function authHeaders(extra) {
  const h = new Headers(extra || {});
  const key = getApiKey();
  if (key) h.set('Authorization', `Bearer ${key}`);
  return h;
}

async function problemOf(res) {
  const type = res.headers.get('content-type') || '';
  let problem = null;
  try {
    if (type.includes('json')) problem = await res.json();
    else {
      const text = await res.text();
      problem = { detail: text.slice(0, 300) || res.statusText };
    }
  } catch {
    problem = null;
  }
  const ra = res.headers.get('retry-after');
  return new ApiError(res.status, problem, ra === null ? null : Number(ra));
}

/** fetch() with the API key; throws ApiError for a non-2xx answer. */
export async function api(path, options = {}) {
  const res = await fetch(path, { ...options, headers: authHeaders(options.headers) });
  if (!res.ok) throw await problemOf(res);
  return res;
}

export async function apiJson(path, options = {}) {
  const res = await api(path, options);
  return { status: res.status, body: await res.json(), headers: res.headers };
}

/** A blob: URL of an authenticated GET (for <img> and downloads, which cannot send headers). */
export async function blobUrl(path, signal) {
  const res = await api(path, { signal });
  return URL.createObjectURL(await res.blob());
}

/**
 * Reads a Server-Sent Events stream with fetch and calls `onEvent(name, data)` for every event
 * (data parsed as JSON when it is JSON). Resolves when the stream ends; rejects on a network or
 * HTTP error (ApiError). `signal` aborts it.
 */
export async function readEvents(path, onEvent, signal) {
  const res = await api(path, { signal, headers: { Accept: 'text/event-stream' } });
  const reader = res.body.getReader();
  const decoder = new TextDecoder();
  let buffer = '';
  let name = '';
  let data = [];
  const dispatch = () => {
    if (data.length) {
      const text = data.join('\n');
      let value = text;
      try {
        value = JSON.parse(text);
      } catch {
        // not JSON: pass the text on
      }
      onEvent(name || 'message', value);
    }
    name = '';
    data = [];
  };
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    buffer += decoder.decode(value, { stream: true });
    // Lines end with \n, \r\n or \r (the SSE grammar allows all three).
    let m;
    while ((m = /\r\n|\n|\r/.exec(buffer)) !== null) {
      // A lone \r at the very end may be the first half of \r\n: wait for more bytes.
      if (m[0] === '\r' && m.index === buffer.length - 1) break;
      const line = buffer.slice(0, m.index);
      buffer = buffer.slice(m.index + m[0].length);
      if (line === '') {
        dispatch();
        continue;
      }
      if (line.startsWith(':')) continue; // comment / keep-alive
      const colon = line.indexOf(':');
      const field = colon < 0 ? line : line.slice(0, colon);
      let val = colon < 0 ? '' : line.slice(colon + 1);
      if (val.startsWith(' ')) val = val.slice(1);
      if (field === 'event') name = val;
      else if (field === 'data') data.push(val);
    }
  }
  dispatch();
}

/**
 * GET of a result that may still be encoding: the server answers 202 + Retry-After at once for
 * a format the bake did not encode, then the file once it is stored. `onPending(body)` is called
 * with each 202's JSON body (`{}` when it has none) before waiting for its Retry-After (≤ 2 s).
 */
export async function fetchResult(path, onPending) {
  for (;;) {
    const res = await api(path);
    if (res.status !== 202) return res;
    const body = await res.json().catch(() => ({}));
    onPending(body);
    const wait = Number(res.headers.get('retry-after')) || 1;
    await new Promise((r) => setTimeout(r, Math.min(wait, 2) * 1000));
  }
}

/**
 * A plain fetch(), without the API key and without `ApiError`: for the server's public files
 * (GET /v1/shaders/…), which need no key; the caller checks `res.ok` itself.
 */
export function fetchPublic(url, options) {
  return fetch(url, options);
}
