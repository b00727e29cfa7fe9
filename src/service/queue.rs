//! The bounded in-memory queue of bake ids and the live state of bakes in flight.
//!
//! The durable truth is the bake store; this queue only orders work. A submission is pushed here
//! after its record is committed, and a restart rebuilds the queue from the records found
//! `queued` or `running` ([`Queue::push_recovered`] ignores the capacity: those bakes were
//! accepted already). Each bake in flight has a [`Live`] entry holding the [`Progress`] the kernel
//! advances and the flag that tells the worker whether a cancellation came from the owner
//! (→ `canceled`) or from shutdown (→ back to `queued`).

use crate::progress::{Progress, Stage};
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use tokio::sync::Notify;

/// A bake in flight (queued or running).
#[derive(Debug, Clone, Default)]
pub struct Live {
    pub progress: Progress,
    /// Set by shutdown: a cancellation means "put it back", not "the owner canceled it".
    pub requeue: Arc<AtomicBool>,
    /// Whether a worker has taken it.
    pub running: bool,
}

#[derive(Debug, Default)]
struct Inner {
    waiting: VecDeque<String>,
    live: HashMap<String, Live>,
}

/// The queue was full.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QueueFull;

/// Bounded FIFO of bake ids plus the live state of every bake in flight.
#[derive(Debug)]
pub struct Queue {
    inner: Mutex<Inner>,
    notify: Notify,
    capacity: usize,
}

impl Queue {
    /// An empty queue holding at most `capacity` waiting bakes.
    pub fn new(capacity: usize) -> Self {
        Queue { inner: Mutex::new(Inner::default()), notify: Notify::new(), capacity }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        // A panic while holding this lock leaves plain data in a consistent state; keep going.
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The configured capacity.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Whether a push would be refused now.
    pub fn is_full(&self) -> bool {
        self.lock().waiting.len() >= self.capacity
    }

    /// Appends a new bake.
    ///
    /// # Errors
    /// [`QueueFull`] when `capacity` bakes are waiting already.
    pub fn try_push(&self, id: &str) -> Result<(), QueueFull> {
        {
            let mut g = self.lock();
            if g.waiting.len() >= self.capacity {
                return Err(QueueFull);
            }
            Self::insert(&mut g, id);
        }
        self.notify.notify_one();
        Ok(())
    }

    /// Appends a bake found unfinished at boot, whatever the capacity.
    pub fn push_recovered(&self, id: &str) {
        Self::insert(&mut self.lock(), id);
        self.notify.notify_one();
    }

    fn insert(g: &mut Inner, id: &str) {
        if g.live.contains_key(id) {
            return;
        }
        let live = Live::default();
        live.progress.start(Stage::Queued, 1);
        g.live.insert(id.to_owned(), live);
        g.waiting.push_back(id.to_owned());
    }

    /// Takes the next waiting bake, marking it running.
    pub fn pop(&self) -> Option<(String, Live)> {
        let mut g = self.lock();
        let id = g.waiting.pop_front()?;
        let live = g.live.get_mut(&id)?;
        live.running = true;
        Some((id, live.clone()))
    }

    /// Waits until a bake is waiting and takes it.
    pub async fn next(&self) -> (String, Live) {
        loop {
            if let Some(x) = self.pop() {
                return x;
            }
            self.notify.notified().await;
        }
    }

    /// Removes a bake that is still waiting; returns whether it was.
    pub fn remove_waiting(&self, id: &str) -> bool {
        let mut g = self.lock();
        let Some(pos) = g.waiting.iter().position(|w| w == id) else {
            return false;
        };
        g.waiting.remove(pos);
        g.live.remove(id);
        true
    }

    /// The live state of a bake in flight.
    pub fn live(&self, id: &str) -> Option<Live> {
        self.lock().live.get(id).cloned()
    }

    /// Asks a running bake to stop; `requeue` says whether it goes back to the queue.
    pub fn cancel_running(&self, id: &str, requeue: bool) -> bool {
        let g = self.lock();
        match g.live.get(id) {
            Some(l) if l.running => {
                if requeue {
                    l.requeue.store(true, Ordering::Relaxed);
                }
                l.progress.cancel();
                true
            }
            _ => false,
        }
    }

    /// Ids of the running bakes.
    pub fn running_ids(&self) -> Vec<String> {
        self.lock().live.iter().filter(|(_, l)| l.running).map(|(k, _)| k.clone()).collect()
    }

    /// Forgets a bake once its worker has recorded the outcome.
    pub fn finish(&self, id: &str) {
        self.lock().live.remove(id);
    }

    /// (waiting, running).
    pub fn counts(&self) -> (usize, usize) {
        let g = self.lock();
        let running = g.live.values().filter(|l| l.running).count();
        (g.waiting.len(), running)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounded_fifo_with_recovery_overflow() {
        let q = Queue::new(2);
        q.try_push("a").unwrap();
        q.try_push("b").unwrap();
        assert_eq!(q.try_push("c"), Err(QueueFull));
        q.push_recovered("r");
        assert_eq!(q.counts(), (3, 0));
        let (id, live) = q.pop().unwrap();
        assert_eq!(id, "a");
        assert!(live.running);
        assert_eq!(q.counts(), (2, 1));
        assert!(q.remove_waiting("b"));
        assert!(!q.remove_waiting("a"));
        assert!(q.cancel_running("a", true));
        assert!(q.live("a").unwrap().progress.is_canceled());
        assert!(q.live("a").unwrap().requeue.load(Ordering::Relaxed));
        q.finish("a");
        assert_eq!(q.pop().unwrap().0, "r");
        assert!(q.pop().is_none());
    }
}
