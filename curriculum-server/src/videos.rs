//! Eval videos sent by eval actors (`rfcl.v1.EvalVideos.Put`): kept as files in `RUN_DIR/videos/`,
//! listed in the dashboard's view and served at `/videos/<name>`. The file name carries what a
//! video shows ([`VideoMeta::file_name`]), so a restarted server lists its videos again from the
//! directory alone.
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use rfcl_core::video::{EvalVideo, VideoMeta};
use rfcl_proto::v1;
use tonic::{Request, Response, Status};

/// The most videos one eval actor keeps; its oldest goes when a newer one comes (a run records one
/// every `eval_env.video_every` evaluations, far fewer than this).
pub const MAX_VIDEOS_PER_ACTOR: usize = 100;
/// The most bytes of videos a run keeps, all actors together; the oldest videos go first.
pub const MAX_VIDEO_BYTES: u64 = 256 << 20;

/// The videos of a run, on disk. Space is bounded per eval actor and in bytes, and a new video
/// always finds room: the oldest ones (by policy version) are evicted, and counted, so a client
/// that floods the store pushes out old videos but never keeps the eval actors' new ones out.
#[derive(Debug)]
pub struct VideoStore {
    /// `RUN_DIR/videos`; `None` for a server without a run directory, which keeps none.
    dir: Option<PathBuf>,
    /// Every kept video and its size in bytes, oldest first.
    index: Mutex<Vec<(VideoMeta, u64)>>,
    /// Videos refused: no run directory, or a failed write.
    refused: AtomicU64,
    /// Videos removed to make room for newer ones.
    evicted: AtomicU64,
}

/// The counts the dashboard shows beside the links.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoListing {
    pub videos: Vec<VideoMeta>,
    pub refused: u64,
    pub evicted: u64,
}

impl VideoStore {
    /// The store of `run_dir`, with the videos already there (a restarted server).
    pub fn open(run_dir: Option<PathBuf>) -> std::io::Result<VideoStore> {
        let dir = run_dir.map(|d| d.join("videos"));
        let mut index = Vec::new();
        if let Some(dir) = dir.as_ref().filter(|d| d.is_dir()) {
            for entry in std::fs::read_dir(dir)? {
                let entry = entry?;
                let name = entry.file_name();
                if let Some(meta) = name.to_str().and_then(VideoMeta::from_file_name) {
                    index.push((meta, entry.metadata()?.len()));
                }
            }
        }
        index.sort_by_key(|(m, _)| (m.policy_version, m.file_name()));
        Ok(VideoStore {
            dir,
            index: Mutex::new(index),
            refused: AtomicU64::new(0),
            evicted: AtomicU64::new(0),
        })
    }

    /// Keeps a video; its name. The same episode sent again replaces its file.
    pub fn put(&self, video: EvalVideo) -> Result<String, Status> {
        let refuse = |status: Status| {
            self.refused.fetch_add(1, Ordering::Relaxed);
            Err(status)
        };
        let Some(dir) = &self.dir else {
            return refuse(Status::failed_precondition(
                "this curriculum server has no run directory to keep eval videos in",
            ));
        };
        let name = video.meta.file_name();
        let bytes = video.gif.len() as u64;
        let mut index = self.index.lock().unwrap_or_else(|p| p.into_inner());
        // The same episode sent again replaces its file.
        index.retain(|(m, _)| m.file_name() != name);
        for old in make_room(&index, &video.meta, bytes) {
            let _ = std::fs::remove_file(dir.join(old.file_name()));
            index.retain(|(m, _)| *m != old);
            self.evicted.fetch_add(1, Ordering::Relaxed);
        }
        let written = std::fs::create_dir_all(dir)
            .and_then(|()| rfcl_core::atomic::atomic_write(&dir.join(&name), &video.gif));
        if let Err(e) = written {
            return refuse(Status::internal(format!(
                "writing {}: {e}",
                dir.join(&name).display()
            )));
        }
        index.push((video.meta, bytes));
        index.sort_by_key(|(m, _)| (m.policy_version, m.file_name()));
        Ok(name)
    }

    pub fn listing(&self) -> VideoListing {
        let index = self.index.lock().unwrap_or_else(|p| p.into_inner());
        VideoListing {
            videos: index.iter().map(|(m, _)| m.clone()).collect(),
            refused: self.refused.load(Ordering::Relaxed),
            evicted: self.evicted.load(Ordering::Relaxed),
        }
    }

    /// The bytes of a kept video; `None` for any name the store does not list (so no path a
    /// client makes up is ever opened).
    pub fn read(&self, name: &str) -> Option<Vec<u8>> {
        let listed = self
            .index
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .iter()
            .any(|(m, _)| m.file_name() == name);
        listed
            .then(|| std::fs::read(self.dir.as_ref()?.join(name)).ok())
            .flatten()
    }
}

/// The videos to remove, oldest first, so that a new video of `bytes` from `new.actor_id` fits:
/// its actor keeps at most [`MAX_VIDEOS_PER_ACTOR`] and the run at most [`MAX_VIDEO_BYTES`].
/// `index` is oldest first.
fn make_room(index: &[(VideoMeta, u64)], new: &VideoMeta, bytes: u64) -> Vec<VideoMeta> {
    let mut evict = Vec::new();
    let same_actor: Vec<&VideoMeta> = index
        .iter()
        .filter(|(m, _)| m.actor_id == new.actor_id)
        .map(|(m, _)| m)
        .collect();
    let over = (same_actor.len() + 1).saturating_sub(MAX_VIDEOS_PER_ACTOR);
    evict.extend(same_actor.into_iter().take(over).cloned());
    let mut total: u64 = index
        .iter()
        .filter(|(m, _)| !evict.contains(m))
        .map(|(_, b)| b)
        .sum::<u64>()
        + bytes;
    for (m, b) in index {
        if total <= MAX_VIDEO_BYTES {
            break;
        }
        if !evict.contains(m) {
            evict.push(m.clone());
            total -= b;
        }
    }
    evict
}

/// The tonic service.
pub struct EvalVideosService {
    pub store: std::sync::Arc<VideoStore>,
}

#[tonic::async_trait]
impl v1::eval_videos_server::EvalVideos for EvalVideosService {
    async fn put(
        &self,
        request: Request<v1::EvalVideo>,
    ) -> Result<Response<v1::EvalVideoAck>, Status> {
        let video = rfcl_proto::convert::eval_video(request.into_inner()).inspect_err(|_| {
            self.store.refused.fetch_add(1, Ordering::Relaxed);
        })?;
        let store = self.store.clone();
        let name = tokio::task::spawn_blocking(move || store.put(video))
            .await
            .map_err(|e| Status::internal(format!("writing the video: {e}")))??;
        Ok(Response::new(v1::EvalVideoAck { name }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn video(version: u64, success: bool) -> EvalVideo {
        EvalVideo {
            meta: VideoMeta {
                policy_version: version,
                env_steps: version * 1000,
                seed: 1_000_000 + version,
                success_at_end: success,
                episode_return: 3.0,
                actor_id: 2,
            },
            gif: format!("GIF89a video {version}").into_bytes(),
        }
    }

    #[test]
    fn videos_are_kept_listed_served_and_found_again_after_a_restart() {
        let dir = tempfile::tempdir().unwrap();
        let store = VideoStore::open(Some(dir.path().into())).unwrap();
        let second = store.put(video(20, true)).unwrap();
        let first = store.put(video(10, false)).unwrap();
        // Sent again: replaced, not listed twice.
        assert_eq!(store.put(video(10, false)).unwrap(), first);
        let listing = store.listing();
        let versions: Vec<u64> = listing.videos.iter().map(|m| m.policy_version).collect();
        assert_eq!(
            (versions, listing.refused, listing.evicted),
            (vec![10, 20], 0, 0)
        );
        assert_eq!(store.read(&second).unwrap(), b"GIF89a video 20");
        // Only listed names are opened.
        std::fs::write(dir.path().join("videos/other.gif"), b"GIF89a").unwrap();
        assert_eq!(store.read("other.gif"), None);
        assert_eq!(store.read("../snapshot.json"), None);

        let again = VideoStore::open(Some(dir.path().into())).unwrap();
        assert_eq!(again.listing().videos, store.listing().videos);
        assert_eq!(again.read(&first).unwrap(), b"GIF89a video 10");
    }

    #[test]
    fn a_flood_evicts_the_oldest_and_never_keeps_a_new_video_out() {
        let dir = tempfile::tempdir().unwrap();
        let store = VideoStore::open(Some(dir.path().into())).unwrap();
        store.put(video(1, true)).unwrap();
        // One client sends far more than an actor may keep, as actor 7.
        for v in 100..100 + MAX_VIDEOS_PER_ACTOR as u64 + 20 {
            let mut flood = video(v, false);
            flood.meta.actor_id = 7;
            store.put(flood).unwrap();
        }
        let listing = store.listing();
        let of = |actor| {
            listing
                .videos
                .iter()
                .filter(|m| m.actor_id == actor)
                .count()
        };
        assert_eq!((of(7), of(2)), (MAX_VIDEOS_PER_ACTOR, 1));
        assert_eq!((listing.evicted, listing.refused), (20, 0));
        // The eval actor's next video is kept, and its first one too (its own quota is not full).
        let newest = store.put(video(500, true)).unwrap();
        assert_eq!(
            store
                .listing()
                .videos
                .iter()
                .filter(|m| m.actor_id == 2)
                .count(),
            2
        );
        assert!(store.read(&newest).is_some());
        // Evicted files are gone from the disk, so a restart lists what the store listed.
        let again = VideoStore::open(Some(dir.path().into())).unwrap();
        assert_eq!(again.listing().videos, store.listing().videos);
    }

    #[test]
    fn the_bytes_a_run_keeps_are_bounded_oldest_first() {
        let meta = |version, actor| VideoMeta {
            actor_id: actor,
            ..video(version, true).meta
        };
        // Three videos of 100 MiB each (two actors): a fourth of 100 MiB pushes the oldest out,
        // whatever its actor, so that 256 MiB hold.
        let mib = 1 << 20;
        let index = vec![
            (meta(1, 2), 100 * mib),
            (meta(2, 3), 100 * mib),
            (meta(3, 2), 50 * mib),
        ];
        assert_eq!(make_room(&index, &meta(4, 3), 100 * mib), vec![meta(1, 2)]);
        assert!(make_room(&index, &meta(4, 3), 6 * mib).is_empty());
    }

    #[test]
    fn without_a_run_directory_videos_are_refused_and_counted() {
        let store = VideoStore::open(None).unwrap();
        let err = store.put(video(1, true)).unwrap_err();
        assert_eq!(err.code(), tonic::Code::FailedPrecondition);
        assert_eq!(store.listing().refused, 1);
    }
}
