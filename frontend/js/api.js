// REST client: JSON fetch with the optional bearer token, readable errors, uploads with progress.

export function getToken() { return localStorage.getItem("aerograv-token") || ""; }
export function setToken(t) { localStorage.setItem("aerograv-token", t || ""); }

function authHeaders() {
  const t = getToken();
  return t ? { Authorization: `Bearer ${t}` } : {};
}

// Turn an error body into one readable line ("file flights/F1/gnss.csv, row 17, column 'vu': ...").
export function describeError(status, body) {
  const d = body && body.detail !== undefined ? body.detail : body;
  if (d && typeof d === "object" && !Array.isArray(d) && "message" in d) {
    const where = [];
    if (d.file) where.push(`file ${d.file}`);
    if (d.row !== null && d.row !== undefined) where.push(`row ${d.row}`);
    if (d.column) where.push(`column '${d.column}'`);
    return (where.length ? where.join(", ") + ": " : "") + d.message;
  }
  if (Array.isArray(d)) {  // pydantic validation errors
    return d.map((e) => `${(e.loc || []).join(".")}: ${e.msg}`).join("\n");
  }
  if (typeof d === "string") return `${d} (HTTP ${status})`;
  return `HTTP ${status}`;
}

export class ApiError extends Error {
  constructor(status, body) { super(describeError(status, body)); this.status = status; this.body = body; }
}

export async function api(path, { method = "GET", json, params } = {}) {
  let url = path;
  if (params) url += "?" + new URLSearchParams(params).toString();
  const opts = { method, headers: { ...authHeaders() } };
  if (json !== undefined) { opts.headers["Content-Type"] = "application/json"; opts.body = JSON.stringify(json); }
  const r = await fetch(url, opts);
  const text = await r.text();
  let body = null;
  try { body = text ? JSON.parse(text) : null; } catch { body = text; }
  if (!r.ok) throw new ApiError(r.status, body);
  return body;
}

// multipart upload with progress (XMLHttpRequest: fetch has no upload progress)
export function upload(path, formData, onProgress, method = "POST") {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open(method, path);
    const h = authHeaders();
    for (const k in h) xhr.setRequestHeader(k, h[k]);
    xhr.upload.onprogress = (e) => { if (e.lengthComputable && onProgress) onProgress(e.loaded / e.total); };
    xhr.onload = () => {
      let body = null;
      try { body = JSON.parse(xhr.responseText); } catch { body = xhr.responseText; }
      if (xhr.status >= 200 && xhr.status < 300) resolve(body); else reject(new ApiError(xhr.status, body));
    };
    xhr.onerror = () => reject(new ApiError(0, "network error during upload"));
    xhr.send(formData);
  });
}

export const endpoints = {
  surveys: () => api("/api/surveys"),
  survey: (id) => api(`/api/surveys/${id}`),
  createSurvey: (name) => api("/api/surveys", { method: "POST", json: { name } }),
  qc: (id) => api(`/api/surveys/${id}/qc`),
  tracks: (id) => api(`/api/surveys/${id}/tracks`),
  lines: (id) => api(`/api/surveys/${id}/lines`),
  profile: (id, line, params) => api(`/api/surveys/${id}/lines/${encodeURIComponent(line)}`, { params }),
  repeatTracks: (id) => api(`/api/surveys/${id}/repeat-tracks`),
  repeatTrack: (id, track, params) => api(`/api/surveys/${id}/repeat-tracks/${encodeURIComponent(track)}`, { params }),
  recognition: (id, params) => api(`/api/surveys/${id}/recognition`, { params }),
  grid: (id, params) => api(`/api/surveys/${id}/grid`, params ? { params } : {}),
  deleteDem: (id) => api(`/api/surveys/${id}/dem`, { method: "DELETE" }),
  report: (id) => api(`/api/surveys/${id}/report`),
  patchSurvey: (id, body) => api(`/api/surveys/${id}`, { method: "PATCH", json: body }),
  deleteSurvey: (id) => api(`/api/surveys/${id}`, { method: "DELETE" }),
  jobs: (id) => api(`/api/surveys/${id}/jobs`),
  job: (jid) => api(`/api/jobs/${jid}`),
  submitJob: (id, kind, params) => api(`/api/surveys/${id}/jobs`, { method: "POST", json: { kind, params } }),
  cancelJob: (jid) => api(`/api/jobs/${jid}/cancel`, { method: "POST" }),
  paramsSchema: () => api("/api/params/schema"),
};
