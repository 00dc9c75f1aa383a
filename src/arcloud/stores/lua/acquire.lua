-- Take every key (locks or space claims, in sorted order) or none: all-or-nothing in one step.
-- KEYS: the lock/claim keys. ARGV[1]: token, ARGV[2]: ttl in milliseconds.
-- Keys already holding this token count as free (a retried call whose reply was lost succeeds).
-- Returns {0} when all were taken, else {i, pttl}: the first busy key (1-based) and its remaining ms; that
-- key is then marked wanted (<key>:wanted, for as long as its holder's ttl) so that its release wakes a
-- waiter (release.lua), who blocks on <key>:wake meanwhile (keys.py).
for i, key in ipairs(KEYS) do
  local holder = redis.call('GET', key)
  if holder and holder ~= ARGV[1] then
    local pttl = redis.call('PTTL', key)
    redis.call('SET', key .. ':wanted', 1, 'PX', math.max(pttl, 1))
    return {i, pttl}
  end
end
for _, key in ipairs(KEYS) do
  redis.call('SET', key, ARGV[1], 'PX', ARGV[2])
end
return {0}
