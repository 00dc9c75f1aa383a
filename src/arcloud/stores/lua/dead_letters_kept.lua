-- Which dead letters are still kept (max_dead_letters and max_dead_letter_bytes drop the oldest), without
-- sending their payloads back.
-- KEYS[1] the dead-letter STREAM. ARGV: entry ids. Returns 1 (kept) or 0 for each, in order.
local kept = {}
for i, entry_id in ipairs(ARGV) do
  kept[i] = #redis.call('XRANGE', KEYS[1], entry_id, entry_id)
end
return kept
