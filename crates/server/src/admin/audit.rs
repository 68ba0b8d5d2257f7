//! Writing the audit trail: every state-changing action (done or not) and every refused
//! request goes to the store's `admin_audit` table before the answer leaves.
//!
//! Refusals come from whoever can reach the port, so they are written at most
//! [`REFUSALS_AUDITED_PER_S`] a second: a flood of bad tokens costs the database a
//! bounded number of rows, and the rest are counted (`audits_suppressed`, and the
//! metric `myriad_admin_audits_suppressed_total`), never lost silently.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use myriad_store::{AuditEntry, Store, now_ms};

use super::{AdminShared, bump};

/// Refused requests written to the audit table per second, at most.
pub(crate) const REFUSALS_AUDITED_PER_S: u32 = 20;

/// The actor of a refused request (it proved nothing about who it is).
pub(crate) const ANONYMOUS: &str = "anonymous";

/// Writes audit entries (cheap to clone).
#[derive(Debug, Clone)]
pub(crate) struct Auditor {
    store: Store,
    shared: Arc<AdminShared>,
    /// The current second (ms since the epoch / 1000) and the refusals written in it.
    refusals: Arc<Mutex<(i64, u32)>>,
}

impl Auditor {
    pub(crate) fn new(store: Store, shared: Arc<AdminShared>) -> Self {
        Auditor { store, shared, refusals: Arc::new(Mutex::new((0, 0))) }
    }

    /// Writes one entry; a failure is logged and counted (the action itself stands).
    pub(crate) async fn record(
        &self,
        actor: &str,
        action: &str,
        target: &str,
        detail: &str,
        from: SocketAddr,
        ok: bool,
    ) {
        let entry = AuditEntry {
            at_ms: now_ms(),
            actor: actor.into(),
            action: action.into(),
            target: target.into(),
            detail: detail.into(),
            from: from.to_string(),
            ok,
        };
        if let Err(e) = self.store.append_audit(&entry).await {
            bump(&self.shared.counters.audit_failures);
            metrics::counter!("myriad_admin_audit_failures_total").increment(1);
            tracing::error!(error = %e, action, target, "audit entry not written");
        }
    }

    /// Writes a refused request (`why`: no token, wrong token, address not allowed),
    /// within the per-second budget.
    pub(crate) async fn refusal(&self, path: &str, why: &str, from: SocketAddr) {
        let second = now_ms() / 1000;
        let within = {
            let mut window = self.refusals.lock().unwrap_or_else(|p| p.into_inner());
            if window.0 != second {
                *window = (second, 0);
            }
            window.1 += 1;
            window.1 <= REFUSALS_AUDITED_PER_S
        };
        if within {
            self.record(ANONYMOUS, "refused", path, why, from, false).await;
        } else {
            bump(&self.shared.counters.audits_suppressed);
            metrics::counter!("myriad_admin_audits_suppressed_total").increment(1);
        }
    }
}
