# The refinement loop for a person with an image editor.
#
#   make -f examples/loop.mk suggest WS=ws          # V, then the next view to paint (prints its file)
#   ... paint ws/suggestions/NNN/suggested.png in GIMP / Krita / Photoshop, save it as EDIT ...
#   make -f examples/loop.mk update WS=ws EDIT=painted.png   # register the painting, refine the avatar
#   make -f examples/loop.mk status WS=ws           # the edits so far and the avatar iterations
#
# Repeat suggest / paint / update about five times. AVATARPERFECT can name another executable.
AVATARPERFECT ?= avatarperfect
WS ?= ws
EDIT ?= edited.png

.PHONY: suggest update status

suggest:
	$(AVATARPERFECT) visibility $(WS)
	$(AVATARPERFECT) suggest $(WS)
	@latest=$$(ls -d $(WS)/suggestions/[0-9]* | tail -n 1); \
	echo; echo "paint $$latest/suggested.png (guide: $$latest/guide.png), save it, then:"; \
	echo "  make -f examples/loop.mk update WS=$(WS) EDIT=path/to/your/painting.png"

update:
	$(AVATARPERFECT) apply-edit $(WS) $(EDIT)
	$(AVATARPERFECT) refine $(WS)
	@echo; echo "avatar: $$(ls $(WS)/avatar/*.ply | tail -n 1); next: make -f examples/loop.mk suggest WS=$(WS)"

status:
	$(AVATARPERFECT) apply-edit $(WS) --list
	@ls $(WS)/avatar
