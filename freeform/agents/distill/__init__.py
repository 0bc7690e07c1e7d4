"""Distillation: per-body teachers trained as one bank (``teachers``), DAgger from them into one student
(``dagger``: ``Distillation``, ``algo=distill``), and a frozen policy's log-likelihood as a reward (``prior``)."""

from freeform.agents.distill.dagger import (
    LOSSES,
    BankTeacher,
    ChosenTeacher,
    Distillation,
    DistillConfig,
    Symmetry,
    Teacher,
    TeacherMixing,
    bank_from_checkpoint,
    distill_loss,
)
from freeform.agents.distill.teachers import TeacherBank, TeacherIndex

__all__ = ["LOSSES", "BankTeacher", "ChosenTeacher", "DistillConfig", "Distillation", "Symmetry", "Teacher",
           "TeacherBank", "TeacherIndex", "TeacherMixing", "bank_from_checkpoint", "distill_loss"]
