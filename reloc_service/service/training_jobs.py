"""A served map's training jobs (:class:`MapTraining`): one at a time, in the background,
apart from snapshots; the new models go to the replicas and into a snapshot."""

from __future__ import annotations

import threading
import time
import uuid

from reloc_client.protocol import EventKind

from .codec import error_of
from .map_snapshots import MapSnapshots
from .runtime_state import TrainingJob


class MapTraining(MapSnapshots):
    """A map's training jobs (see module docstring)."""

    # -- training --------------------------------------------------------------------------------
    def start_training(self, method: str | None) -> tuple[str, bool]:
        """Start a training job (``method`` or every served method); (job id, started). A job
        already running is reported with its id and started=False."""
        with self._job_lock:
            if self._job is not None:
                return self._job.job_id, False
            methods = (method,) if method is not None else self.methods
            job = TrainingJob(uuid.uuid4().hex[:12], methods, started=time.time())
            job.thread = threading.Thread(target=self._train, args=(job,),
                                          name=f"train-{self.name}", daemon=True)
            self._job = job
            job.thread.start()
            return job.job_id, True

    def _train(self, job: TrainingJob) -> None:
        start = time.perf_counter()
        try:
            with self._maintenance:
                self.publish(EventKind.TRAIN_STARTED, job_id=job.job_id, instance=self.instance,
                             method=",".join(job.methods) if len(job.methods) == 1
                             else " ".join(job.methods))
                for i, method in enumerate(job.methods):
                    self.publish(EventKind.TRAIN_PROGRESS, job_id=job.job_id,
                                 fraction=i / len(job.methods), stage=f"training {method}")
                    self.engine.train([method])
                if self.replicas is not None:   # the new models, before train_done
                    self.replicas.rebase(self)
                self.publish(EventKind.TRAIN_PROGRESS, job_id=job.job_id, fraction=1.0,
                             stage="done")
        except Exception as exc:
            code, message = error_of(exc)
            self.publish(EventKind.TRAIN_FAILED, job_id=job.job_id, code=code.value,
                         message=message)
            with self._job_lock:
                self._job = None
            return
        # The snapshot starts before the job ends: a map with neither running may be closed
        # as idle (max_resident_mb), and its models must be on disk by then.
        self.start_snapshot()   # the trained models survive a restart
        with self._job_lock:
            self._job = None
        self.publish(EventKind.TRAIN_DONE, job_id=job.job_id,
                     duration_s=time.perf_counter() - start, map_version=self.map_state().version)

    def training_thread(self) -> threading.Thread | None:
        with self._job_lock:
            return None if self._job is None else self._job.thread
