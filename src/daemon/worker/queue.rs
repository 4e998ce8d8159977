//! The subscriber side of a structure's queue: what a Zenoh callback (or the thread fetching
//! a publisher's cache) does with a payload, by its size and the room left in the queue.

use std::sync::atomic::Ordering;
use std::sync::mpsc::{SyncSender, TrySendError};
use std::time::{Duration, Instant};

use chrono::Utc;
use zenoh::bytes::ZBytes;

use super::Input;
use crate::contract::rejected::REJECTED_PAYLOAD_LIMIT;
use crate::contract::wire::digest_parts;
use crate::daemon::metrics::Shared;

/// What [`enqueue`] does with a set that does not fit the queue.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WhenFull {
    /// Drop it and count it (live sets: the Zenoh callback must not block).
    Drop,
    /// Wait for room (sets fetched from a publisher's cache, on their own thread), for at
    /// most [`QUEUE_WAIT`], then drop and count it.
    Wait,
}

/// How long [`WhenFull::Wait`] waits for room in the queue.
pub const QUEUE_WAIT: Duration = Duration::from_secs(60);

/// The subscriber side of the queue: a payload over the size limit is passed on as its
/// start and digest only; a set that does not fit the queue (by count or by bytes) is
/// dropped and counted, or waited for (`when_full`).
pub fn enqueue(tx: &SyncSender<Input>, shared: &Shared, payload: &ZBytes, when_full: WhenFull) {
    enqueue_as(tx, shared, payload, when_full, Kind::Set);
}

/// [`enqueue`] for a raw block (`boltwatch/<s>/accel`), handed to the accel front.
pub fn enqueue_accel(tx: &SyncSender<Input>, shared: &Shared, payload: &ZBytes) {
    enqueue_as(tx, shared, payload, WhenFull::Drop, Kind::Accel);
}

/// [`enqueue`] for an environment reading (`boltwatch/<s>/environment`).
pub fn enqueue_environment(tx: &SyncSender<Input>, shared: &Shared, payload: &ZBytes) {
    enqueue_as(tx, shared, payload, WhenFull::Wait, Kind::Environment);
}

/// What a queued payload is.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Kind {
    Set,
    Accel,
    Environment,
}

/// [`enqueue`] for a payload of any [`Kind`].
fn enqueue_as(
    tx: &SyncSender<Input>,
    shared: &Shared,
    payload: &ZBytes,
    when_full: WhenFull,
    kind: Kind,
) {
    shared.received.fetch_add(1, Ordering::Relaxed);
    let received = Utc::now();
    if kind != Kind::Environment {
        shared
            .last_received_ms
            .store(received.timestamp_millis().max(0) as u64, Ordering::Relaxed);
    }
    let size = payload.len();
    let deadline = Instant::now() + QUEUE_WAIT;
    let input = if size > shared.max_payload {
        let mut head = Vec::with_capacity(REJECTED_PAYLOAD_LIMIT);
        for slice in payload.slices() {
            let room = REJECTED_PAYLOAD_LIMIT - head.len();
            head.extend_from_slice(&slice[..slice.len().min(room)]);
        }
        Input::Oversize {
            received,
            size,
            head,
            digest: digest_parts(payload.slices()),
        }
    } else {
        while shared.queued_bytes.load(Ordering::Relaxed) + size as u64 > shared.queue_bytes {
            if when_full == WhenFull::Drop || Instant::now() >= deadline {
                shared.dropped.fetch_add(1, Ordering::Relaxed);
                return;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        shared
            .queued_bytes
            .fetch_add(size as u64, Ordering::Relaxed);
        let payload = payload.to_bytes().into_owned();
        match kind {
            Kind::Accel => Input::Accel { received, payload },
            Kind::Environment => Input::Environment { received, payload },
            Kind::Set => Input::Set { received, payload },
        }
    };
    shared.depth.fetch_add(1, Ordering::Relaxed);
    let bytes = input.queued_bytes();
    let sent = send(tx, input, when_full, deadline);
    if !sent {
        shared.depth.fetch_sub(1, Ordering::Relaxed);
        shared.queued_bytes.fetch_sub(bytes, Ordering::Relaxed);
        shared.dropped.fetch_add(1, Ordering::Relaxed);
    }
}

/// Puts `input` in the queue, at once ([`WhenFull::Drop`]) or waiting for room until
/// `deadline` ([`WhenFull::Wait`]); whether it went in.
fn send(tx: &SyncSender<Input>, input: Input, when_full: WhenFull, deadline: Instant) -> bool {
    match when_full {
        WhenFull::Drop => tx.try_send(input).is_ok(),
        WhenFull::Wait => {
            let mut input = input;
            loop {
                match tx.try_send(input) {
                    Ok(()) => break true,
                    Err(TrySendError::Full(back)) if Instant::now() < deadline => {
                        input = back;
                        std::thread::sleep(Duration::from_millis(5));
                    }
                    Err(_) => break false,
                }
            }
        }
    }
}
