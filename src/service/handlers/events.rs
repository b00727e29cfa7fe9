//! `GET /v1/bakes/{id}/events`: Server-Sent Events of a bake, fed by the jobs core's change
//! feed (every node sees every change) and a short re-read.

#![allow(clippy::result_large_err)]

use super::*;

pub(super) async fn snapshot(st: &AppState, id: &str) -> Option<(Status, Value)> {
    let rec = st.0.jobs.get(id).await.ok().flatten()?;
    let res = resource(st, &rec);
    let status = res.get("status").and_then(Value::as_str).and_then(|s| Status::parse(s).ok())?;
    Some((status, res))
}

pub(super) struct Watch {
    st: AppState,
    id: String,
    rx: tokio::sync::broadcast::Receiver<String>,
    closing: tokio_util::sync::CancellationToken,
    last: Option<String>,
    first: bool,
    done: bool,
    /// Sequence number of the next event (the SSE `id:` field).
    seq: u64,
}

impl Watch {
    /// The next event with its `id:`; the first one also carries `retry:` (how long a client
    /// waits before reconnecting after the stream ends without `done`, e.g. a network cut).
    fn event(&mut self, name: &str, data: String) -> Event {
        let mut ev = Event::default().event(name).data(data).id(self.seq.to_string());
        if self.seq == 0 {
            ev = ev.retry(Duration::from_millis(2000));
        }
        self.seq += 1;
        ev
    }
}

/// `GET /v1/bakes/{id}/events`: `progress` events while the bake is in flight, `encoding`
/// events while a result of the finished bake is encoded after its first download, then one
/// `done` event carrying the final resource (or `deleted`), then the stream ends. Every stream ends
/// with `done`: on shutdown too, carrying the resource as it stands (still queued or running,
/// it finishes after the restart), so a client never waits on a stream that silently stopped.
pub async fn events(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, Problem> {
    load(&st, &id).await?;
    let rx = st.0.jobs.watch();
    let closing = st.0.jobs.closing();
    let w = Watch { st, id, rx, closing, last: None, first: true, done: false, seq: 0 };
    let stream = futures_util::stream::unfold(w, |mut w| async move {
        if w.done {
            return None;
        }
        loop {
            let mut closing = false;
            if !w.first {
                tokio::select! {
                    _ = w.closing.cancelled() => closing = true,
                    _ = tokio::time::sleep(Duration::from_millis(250)) => {}
                    _ = w.rx.recv() => {}
                }
            }
            w.first = false;
            match snapshot(&w.st, &w.id).await {
                None => {
                    w.done = true;
                    let gone = Deleted { id: &w.id };
                    let ev = w.event("deleted", serde_json::to_string(&gone).unwrap_or_default());
                    return Some((Ok(ev), w));
                }
                Some((status, res)) if status.is_terminal() || closing => {
                    // A download started an encode of this bake's results: show its progress
                    // before `done`, so a client sees the result it waits for come.
                    let running = results::encoding_of(&w.st, &w.id);
                    if !running.is_empty() && !closing {
                        let encoding: Vec<EncodingItem> = running
                            .iter()
                            .map(|j| EncodingItem {
                                result: &j.result,
                                fraction: j.fraction(),
                                stage: j.progress.stage(),
                            })
                            .collect();
                        let text =
                            serde_json::to_string(&EncodingEvent { id: &w.id, status, encoding })
                                .unwrap_or_default();
                        if w.last.as_ref() != Some(&text) {
                            w.last = Some(text.clone());
                            let ev = w.event("encoding", text);
                            return Some((Ok(ev), w));
                        }
                        continue;
                    }
                    w.done = true;
                    let ev = w.event("done", res.to_string());
                    return Some((Ok(ev), w));
                }
                Some((status, res)) => {
                    let text = serde_json::to_string(&ProgressEvent {
                        id: &w.id,
                        status,
                        progress: &res["progress"],
                    })
                    .unwrap_or_default();
                    if w.last.as_ref() != Some(&text) {
                        w.last = Some(text.clone());
                        let ev = w.event("progress", text);
                        return Some((Ok(ev), w));
                    }
                }
            }
        }
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

/// The data of a `progress` event.
#[derive(serde::Serialize)]
struct ProgressEvent<'a> {
    id: &'a str,
    status: Status,
    progress: &'a Value,
}

/// The data of an `encoding` event: results of a finished bake being encoded after a download
/// asked for them.
#[derive(serde::Serialize)]
struct EncodingEvent<'a> {
    id: &'a str,
    status: Status,
    encoding: Vec<EncodingItem<'a>>,
}

#[derive(serde::Serialize)]
struct EncodingItem<'a> {
    result: &'a str,
    fraction: f64,
    stage: Stage,
}

/// The data of a `deleted` event.
#[derive(serde::Serialize)]
struct Deleted<'a> {
    id: &'a str,
}
