//! The process table of `rfcl train`: the curriculum server, the learner and the actors it
//! started, how each is started again, and `RUN_DIR/processes.json`. What to do when one exits is
//! the restart policy's ([`super::policy`]); this module starts, reaps and stops.
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::ExitStatus;

use anyhow::{bail, Context, Result};
use rfcl_core::config::RunConfig;
use rfcl_core::ready::ReadyLine;

use super::children::{describe, Child, Launcher};
use super::policy::{ActorDecision, RestartPolicy, Service};
use super::progress::split_envs;
use super::{write_json, ACTOR_GRACE, LEARNER_GRACE, READY_TIMEOUT, SERVER_GRACE};

/// Where the services answer.
#[derive(Debug, Clone)]
pub struct Addresses {
    /// `http://host:port` of the curriculum server's gRPC.
    pub curriculum: String,
    /// `http://host:port` of the learner's gRPC.
    pub learner: String,
    pub dashboard: String,
}

/// An actor process and how to restart it.
struct ActorProc {
    id: u32,
    eval: bool,
    envs: u32,
    child: Option<Child>,
    /// Exited by itself with success (the curriculum finished): not respawned.
    done: bool,
}

impl ActorProc {
    fn name(&self) -> String {
        if self.eval {
            format!("eval-actor-{}", self.id)
        } else {
            format!("actor-{}", self.id)
        }
    }
}

/// What became of an actor that exited.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ActorExit {
    /// Exited with success: the curriculum hands out no more leases.
    Finished { name: String },
    /// Died and was started again.
    Respawned {
        name: String,
        pid: u32,
        cause: String,
        tail: String,
    },
}

/// The children of a session.
pub struct Supervisor {
    launcher: Launcher,
    run_dir: PathBuf,
    server: Child,
    learner: Option<Child>,
    /// How each service is started again: on the port it had, from the run directory (which
    /// holds its snapshot or checkpoint).
    server_args: Vec<OsString>,
    learner_args: Vec<OsString>,
    pub addrs: Addresses,
    actors: Vec<ActorProc>,
    pub policy: RestartPolicy,
}

/// What the services are started with.
pub struct ServiceInputs<'a> {
    pub cfg: &'a RunConfig,
    pub run_dir: &'a Path,
    pub config_path: &'a Path,
    pub demos: &'a Path,
    pub learner_threads: u32,
    pub resume: bool,
}

fn os(args: &[&str]) -> Vec<OsString> {
    args.iter().map(OsString::from).collect()
}

impl Supervisor {
    /// Starts the curriculum server, then the learner, each waited for until ready; the learner's
    /// ready line comes back with the supervisor (it names the metrics endpoint). Actors are
    /// started by [`Supervisor::start_actors`].
    pub async fn start(inputs: ServiceInputs<'_>, launcher: Launcher) -> Result<(Self, ReadyLine)> {
        let cfg = inputs.cfg;
        let run_dir = inputs.run_dir.as_os_str().to_owned();
        let config = inputs.config_path.as_os_str().to_owned();
        let demos = inputs.demos.as_os_str().to_owned();

        let server_args = |port: &str, dashboard_port: &str, resume: bool| {
            let mut args = vec![
                "--config".into(),
                config.clone(),
                "--demos".into(),
                demos.clone(),
            ];
            args.extend(os(&["--port", port, "--dashboard-port", dashboard_port]));
            args.push(if resume { "--resume" } else { "--run-dir" }.into());
            args.push(run_dir.clone());
            args
        };
        let mut server = launcher.spawn(
            "curriculum-server",
            "curriculum-server",
            server_args(
                &cfg.service.curriculum_port.to_string(),
                &cfg.service.dashboard_port.to_string(),
                inputs.resume,
            ),
        )?;
        let line = server.ready_line(READY_TIMEOUT).await?;
        let (Some(curriculum_addr), Some(dashboard)) =
            (line.field("grpc"), line.field("dashboard"))
        else {
            bail!("unexpected ready line from the curriculum server: {line}");
        };
        let (curriculum_addr, dashboard) = (curriculum_addr.to_owned(), dashboard.to_owned());
        let curriculum_url = format!("http://{curriculum_addr}");
        // A restarted server resumes from the run directory's snapshot on the same ports, where
        // the learner and the actors look for it.
        let server_args = server_args(
            &port_of(&curriculum_addr)?.to_string(),
            &port_of(&dashboard)?.to_string(),
            false,
        );

        let learner_args = |port: &str, resume: bool| {
            let mut args = vec![
                "--config".into(),
                config.clone(),
                "--demos".into(),
                demos.clone(),
            ];
            args.extend(os(&[
                "--curriculum",
                &curriculum_url,
                "--port",
                port,
                "--threads",
                &inputs.learner_threads.to_string(),
                // Prometheus /metrics on a free port (its URL is on the ready line).
                "--metrics-port",
                "0",
            ]));
            args.push(if resume { "--resume" } else { "--run-dir" }.into());
            args.push(run_dir.clone());
            args
        };
        let mut learner = launcher.spawn(
            "learner",
            "learner",
            learner_args(&cfg.service.learner_port.to_string(), inputs.resume),
        )?;
        let learner_line = learner.ready_line(READY_TIMEOUT).await?;
        let Some(learner_addr) = learner_line.field("grpc").map(str::to_owned) else {
            bail!("unexpected ready line from the learner: {learner_line}");
        };
        let learner_args = learner_args(&port_of(&learner_addr)?.to_string(), false);

        // Actors: ids 0.. for training, then the eval actors.
        let s = &cfg.service;
        let mut actors = Vec::new();
        for (i, envs) in split_envs(cfg.env.num_envs, s.num_actors)
            .into_iter()
            .enumerate()
        {
            actors.push((i as u32, false, envs));
        }
        if s.num_eval_actors > 0 {
            for (j, envs) in split_envs(cfg.eval_env.num_envs, s.num_eval_actors)
                .into_iter()
                .enumerate()
            {
                actors.push((s.num_actors + j as u32, true, envs));
            }
        }
        let supervisor = Self {
            launcher,
            run_dir: inputs.run_dir.to_path_buf(),
            server,
            learner: Some(learner),
            server_args,
            learner_args,
            addrs: Addresses {
                curriculum: curriculum_url,
                learner: format!("http://{learner_addr}"),
                dashboard,
            },
            actors: actors
                .into_iter()
                .map(|(id, eval, envs)| ActorProc {
                    id,
                    eval,
                    envs,
                    child: None,
                    done: false,
                })
                .collect(),
            policy: RestartPolicy::default(),
        };
        Ok((supervisor, learner_line))
    }

    /// Starts every actor and writes `processes.json`.
    pub fn start_actors(&mut self) -> Result<()> {
        for i in 0..self.actors.len() {
            self.spawn_actor(i)?;
        }
        self.write_processes()
    }

    fn spawn_actor(&mut self, index: usize) -> Result<()> {
        let a = &self.actors[index];
        let mut args = os(&[
            "--connect",
            &self.addrs.learner,
            "--envs",
            &a.envs.to_string(),
            "--id",
            &a.id.to_string(),
        ]);
        if a.eval {
            args.push("--eval".into());
        }
        let child = self.launcher.spawn(&a.name(), "actor", args)?;
        self.actors[index].child = Some(child);
        Ok(())
    }

    /// `RUN_DIR/processes.json`: the services' addresses and every running child's name and pid
    /// (removed when the session ends).
    pub fn write_processes(&self) -> Result<()> {
        let mut list = vec![serde_json::json!({"name": self.server.name, "pid": self.server.pid})];
        if let Some(l) = &self.learner {
            list.push(serde_json::json!({"name": l.name, "pid": l.pid}));
        }
        for a in &self.actors {
            if let Some(c) = &a.child {
                list.push(serde_json::json!({"name": c.name, "pid": c.pid, "actor_id": a.id, "eval": a.eval}));
            }
        }
        let doc = serde_json::json!({
            "rfcl_pid": std::process::id(),
            "curriculum": self.addrs.curriculum,
            "dashboard": self.addrs.dashboard,
            "learner": self.addrs.learner,
            // The run's token lives in this file, never in processes.json itself.
            "token_file": self.run_dir.join("token"),
            "children": list,
        });
        write_json(&self.run_dir.join("processes.json"), &doc)
    }

    /// The running child of `service` (the learner is `None` once it ended the run).
    pub fn child(&self, service: Service) -> Option<&Child> {
        match service {
            Service::Curriculum => Some(&self.server),
            Service::Learner => self.learner.as_ref(),
        }
    }

    /// The exit status of `service` if it has exited.
    pub fn try_wait(&mut self, service: Service) -> Option<ExitStatus> {
        match service {
            Service::Curriculum => self.server.try_wait(),
            Service::Learner => self.learner.as_mut()?.try_wait(),
        }
    }

    /// The learner exited by itself with success (the end of its budget): forgets it; its pid.
    pub fn learner_ended(&mut self) -> Option<u32> {
        self.learner.take().map(|l| l.pid)
    }

    /// The last lines of `service`'s log.
    pub fn log_tail(&self, service: Service) -> String {
        self.child(service).map(Child::log_tail).unwrap_or_default()
    }

    /// Starts `service` again, on its port, from the run directory; the caller waits for its
    /// ready line and hands it to [`Supervisor::replace`].
    pub fn spawn_again(&self, service: Service) -> Result<Child> {
        let args = match service {
            Service::Curriculum => self.server_args.clone(),
            Service::Learner => self.learner_args.clone(),
        };
        self.launcher.spawn(service.name(), service.name(), args)
    }

    /// `child`, started again and ready, takes the place of the dead `service`.
    pub fn replace(&mut self, service: Service, child: Child) -> Result<()> {
        match service {
            Service::Curriculum => self.server = child,
            Service::Learner => self.learner = Some(child),
        }
        self.write_processes()
    }

    /// Reaps the actors that exited at run wall time `now` and respawns the dead ones; an error
    /// when one keeps dying (the policy gives up), naming it with its log's tail.
    pub fn reap_actors(&mut self, now: f64) -> Result<Vec<ActorExit>> {
        let mut exits = Vec::new();
        for i in 0..self.actors.len() {
            let Some(child) = self.actors[i].child.as_mut() else {
                continue;
            };
            let Some(status) = child.try_wait() else {
                continue;
            };
            let name = child.name.clone();
            let tail = child.log_tail();
            self.actors[i].child = None;
            match self
                .policy
                .actor_exited(self.actors[i].id, status.success(), now)
            {
                ActorDecision::Finished => {
                    self.actors[i].done = true;
                    exits.push(ActorExit::Finished { name });
                }
                ActorDecision::GiveUp => bail!(
                    "{name} keeps dying ({}); stopping the run{tail}",
                    describe(Some(status))
                ),
                ActorDecision::Respawn => {
                    self.spawn_actor(i)?;
                    let pid = self.actors[i].child.as_ref().map_or(0, |c| c.pid);
                    exits.push(ActorExit::Respawned {
                        name,
                        pid,
                        cause: describe(Some(status)),
                        tail,
                    });
                }
            }
        }
        if !exits.is_empty() {
            self.write_processes()?;
        }
        Ok(exits)
    }

    /// Every training actor exited with success.
    pub fn train_actors_done(&self) -> bool {
        self.actors.iter().filter(|a| !a.eval).all(|a| a.done)
    }

    /// Whether any eval actor still runs.
    pub fn eval_actors_running(&mut self) -> bool {
        self.actors
            .iter_mut()
            .filter(|a| a.eval)
            .any(|a| a.child.as_mut().is_some_and(|c| c.try_wait().is_none()))
    }

    /// Stops the training actors (the eval actors go on).
    pub async fn stop_train_actors(&mut self) {
        for actor in self.actors.iter_mut().filter(|a| !a.eval) {
            if let Some(child) = actor.child.as_mut() {
                child.stop(ACTOR_GRACE).await;
            }
        }
    }

    /// Stops the actors, then the learner (it saves its final checkpoint): the learner's pid, if
    /// it was running.
    pub async fn stop_actors_and_learner(&mut self) -> Option<u32> {
        for a in &mut self.actors {
            if let Some(c) = a.child.as_mut() {
                c.stop(ACTOR_GRACE).await;
            }
        }
        let l = self.learner.as_mut()?;
        l.stop(LEARNER_GRACE).await;
        Some(l.pid)
    }

    /// Stops the curriculum server (it saves its snapshot) and removes `processes.json`.
    pub async fn stop_server(&mut self) {
        self.server.stop(SERVER_GRACE).await;
        let _ = std::fs::remove_file(self.run_dir.join("processes.json"));
    }
}

/// The port of `host:port` or `http://host:port/`.
fn port_of(addr: &str) -> Result<u16> {
    addr.trim_end_matches('/')
        .rsplit(':')
        .next()
        .and_then(|p| p.parse().ok())
        .with_context(|| format!("no port in the service address {addr:?}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_port_is_read_from_an_address_or_a_url() {
        assert_eq!(port_of("127.0.0.1:50051").unwrap(), 50051);
        assert_eq!(port_of("http://127.0.0.1:8080/").unwrap(), 8080);
        let e = port_of("localhost").unwrap_err().to_string();
        assert!(
            e.contains("no port in the service address \"localhost\""),
            "{e}"
        );
    }
}
