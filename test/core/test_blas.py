"""The back end's hold on the process's BLAS threads."""

from __future__ import annotations

import importlib

from threadpoolctl import threadpool_limits

from h2o_slam.core.blas import LAZY_BLAS, blas_threads
from h2o_slam.core.online import OnlineConfig, OnlineH2O


def test_a_solver_holds_every_blas_to_one_thread_until_it_closes() -> None:
    importlib.import_module(LAZY_BLAS[0])  # every BLAS the back end loads
    with threadpool_limits(limits=2, user_api="blas"):
        assert len(blas_threads()) >= 2 and set(blas_threads()) == {2}
        h2o = OnlineH2O(planar=True, online=OnlineConfig(background="off"))
        try:
            assert set(blas_threads()) == {1}
        finally:
            h2o.close()
        assert set(blas_threads()) == {2}


def test_a_solver_configured_to_leave_blas_alone_does() -> None:
    with threadpool_limits(limits=2, user_api="blas"):
        h2o = OnlineH2O(planar=True, online=OnlineConfig(background="off", blas_threads=None))
        try:
            assert set(blas_threads()) == {2}
        finally:
            h2o.close()
