//! The actor's side of the fragment ledger (`--ledger FILE`, `junction_common::ledger`): what
//! this process produced and handed to which connection, so a reconciliation can tell a
//! fragment lost with a killed actor from one lost on a broken link or trained on.

use junction_common::fragment::RolloutFragment;
use junction_common::ledger::{Event, Ledger, instance_id};

/// This actor process's ledger and the instance id that names it there and at registration.
#[derive(Debug)]
pub struct FragmentLog {
    ledger: Ledger,
    instance: String,
}

impl FragmentLog {
    /// No ledger; the instance id is still sent at registration.
    pub fn off(name: &str) -> Self {
        FragmentLog {
            ledger: Ledger::off(),
            instance: instance_id(name),
        }
    }

    /// Appends to `path` and records this process's start.
    pub fn open(path: &std::path::Path, name: &str, transport: &str) -> std::io::Result<Self> {
        let log = FragmentLog {
            ledger: Ledger::open(path)?,
            instance: instance_id(name),
        };
        log.ledger.record(&Event::ActorStart {
            instance: &log.instance,
            transport,
            name,
            pid: std::process::id(),
        });
        Ok(log)
    }

    pub fn instance(&self) -> &str {
        &self.instance
    }

    pub fn produced(&self, fragment: &RolloutFragment) {
        self.ledger.record(&Event::Produced {
            instance: &self.instance,
            seq: fragment.sequence,
            agent_steps: fragment.agent_steps() as u64,
        });
    }

    pub fn sent(&self, seq: u64, connection: u64) {
        self.ledger.record(&Event::Sent {
            instance: &self.instance,
            seq,
            connection,
        });
    }

    pub fn confirmed(&self, connection: u64, fragments: u64) {
        self.ledger.record(&Event::Confirmed {
            instance: &self.instance,
            connection,
            fragments,
        });
    }

    pub fn unconfirmed(&self, connection: u64, fragments: u64) {
        self.ledger.record(&Event::Unconfirmed {
            instance: &self.instance,
            connection,
            fragments,
        });
    }

    /// The process ends by itself (not killed): what it produced and never sent stays unsent.
    pub fn stop(&self) {
        self.ledger.record(&Event::ActorStop {
            instance: &self.instance,
        });
    }
}
